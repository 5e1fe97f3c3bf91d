# The simulator image: sim-server with SUMO (libsumo + eclipse-sumo wheels, extra `server`).
# No torch, no learner code. Build from the repository root:
#   docker build -f docker/server.Dockerfile -t av-bridge-server .
# Build arguments:
#   BASE            a Python 3.11 image (default python:3.11-slim; any Debian-like base with
#                   python3 and its venv module works)
#   PIP_EXTRA_ARGS  extra `pip install` arguments (a mirror, --find-links, --cert ...)
#   EXTRAS          the project's extras to install (default server; server,highway adds the
#                   highway-env backend, sim-server --backend highway)
# See docs/docker.md.
ARG BASE=python:3.11-slim

FROM ${BASE} AS build
ARG EXTRAS=server
ARG PIP_EXTRA_ARGS=""
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python3 -m venv /opt/av-bridge
COPY pyproject.toml README.md /src/
COPY protocol /src/protocol
COPY sim_server /src/sim_server
# Only protocol/ and sim_server/ are copied, so the agent-client launcher would be a dead
# script here: remove it. The libsumo and eclipse-sumo wheels each bundle the same ~230 MB of
# shared libraries: replace libsumo's byte-identical copies by symbolic links.
RUN /opt/av-bridge/bin/python -m pip install ${PIP_EXTRA_ARGS} "/src[${EXTRAS}]" \
    && rm /opt/av-bridge/bin/agent-client \
    && cd "$(/opt/av-bridge/bin/python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')" \
    && for lib in libsumo.libs/*; do \
        twin="eclipse_sumo.libs/${lib##*/}"; \
        if cmp -s "$lib" "$twin"; then ln -sf "../$twin" "$lib"; fi; \
    done

FROM ${BASE}
LABEL org.opencontainers.image.title="av-bridge sim-server" \
      org.opencontainers.image.description="SUMO (libsumo) behind the av-bridge protocol (ZeroMQ/msgpack)"
ENV PATH=/opt/av-bridge/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1
# The libsumo wheel is a GUI-enabled build: its module links libX11, libXext, libXrender and
# libGL (never used headless, but needed to load), and netconvert links libatomic. On Debian,
# libgl1 pulls in Mesa and LLVM: this layer is about 350 MB.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libx11-6 libxext6 libxrender1 libgl1 libatomic1 \
    && rm -rf /var/lib/apt/lists/*
COPY --from=build /opt/av-bridge /opt/av-bridge
# SUMO loads, the bridge imports, and there is no torch.
RUN python -c "import libsumo, sumo, zmq, msgpack, sim_server.cli" \
    && ! python -c "import torch" 2>/dev/null
COPY docker/prebuild_scenarios.py /opt/av-bridge/share/prebuild_scenarios.py
# A fixed uid shared with the learner image: both read the CURVE keys of one volume (/keys),
# whose secret files only their owner may read.
RUN useradd --uid 10001 --create-home --shell /usr/sbin/nologin app \
    && mkdir /keys && chown app:app /keys
USER app
WORKDIR /home/app
# netconvert the built-in scenarios now (< 1 s) so that the first reset does not.
RUN python /opt/av-bridge/share/prebuild_scenarios.py
EXPOSE 5555
ENTRYPOINT ["sim-server"]
# Binding a non-loopback address needs authentication: add
#   --secret-key /keys/server.key_secret --authorized-keys /keys
# (keys from `docker run --rm -v KEYS:/keys av-bridge-server keygen --out /keys`), or --insecure
# on a network you trust.
CMD ["--bind", "tcp://0.0.0.0:5555"]
