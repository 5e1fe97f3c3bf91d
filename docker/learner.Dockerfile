# The learner image: agent-client with torch (CPU), gymnasium, matplotlib, scipy, tensorboard
# (extra `client`). No SUMO, no simulator code. Build from the repository root:
#   docker build -f docker/learner.Dockerfile -t av-bridge-learner .
# Build arguments:
#   BASE            a Python 3.11 image (default python:3.11-slim)
#   PIP_EXTRA_ARGS  extra `pip install` arguments. The default adds PyTorch's CPU index, so that
#                   torch==2.13.0 resolves to the CPU build (2.13.0+cpu, ~0.2 GB download) and
#                   not to PyPI's CUDA build with its multi-GB nvidia-* dependencies. To use a
#                   wheel on disk instead: --build-arg PIP_EXTRA_ARGS="--find-links /wheels"
#                   and mount the folder into the build (podman build -v DIR:/wheels:ro).
#   EXTRAS          the project's extras to install (default client)
# See docs/docker.md.
ARG BASE=python:3.11-slim

FROM ${BASE} AS build
ARG EXTRAS=client
ARG PIP_EXTRA_ARGS="--extra-index-url https://download.pytorch.org/whl/cpu"
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python3 -m venv /opt/av-bridge
COPY pyproject.toml README.md /src/
COPY protocol /src/protocol
COPY agent_client /src/agent_client
# Only protocol/ and agent_client/ are copied, so the sim-server launcher would be a dead
# script here: remove it. Then check the image is CPU-only and SUMO-free.
RUN /opt/av-bridge/bin/python -m pip install ${PIP_EXTRA_ARGS} "/src[${EXTRAS}]" \
    && rm /opt/av-bridge/bin/sim-server \
    && /opt/av-bridge/bin/python -c "import torch, gymnasium, agent_client.cli.main; \
assert torch.version.cuda is None, 'torch is a CUDA build: ' + torch.__version__" \
    && ! /opt/av-bridge/bin/python -c "import libsumo" 2>/dev/null \
    && ! /opt/av-bridge/bin/pip list 2>/dev/null | grep -i '^nvidia-'

FROM ${BASE}
LABEL org.opencontainers.image.title="av-bridge agent-client" \
      org.opencontainers.image.description="DDPG/TD3 learner and IDM driver for av-bridge (torch CPU, no SUMO)"
ENV PATH=/opt/av-bridge/bin:$PATH \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    MPLBACKEND=Agg
COPY --from=build /opt/av-bridge /opt/av-bridge
# resolve-servers: one --server per address of a DNS name (docker compose --scale server=N).
COPY --chmod=0755 docker/resolve-servers.sh /usr/local/bin/resolve-servers
# The same uid as the server image (see there): both read the keys of one volume.
RUN useradd --uid 10001 --create-home --shell /usr/sbin/nologin app \
    && mkdir /keys /home/app/runs && chown app:app /keys /home/app/runs
# The tuned settings (`agent-client train --config configs/cf.toml` from the working directory),
# read-only; copied after the user exists, so that its home stays its own.
COPY configs /home/app/configs
USER app
# `agent-client train` writes runs/NAME here by default: mount a volume on /home/app/runs.
WORKDIR /home/app
ENTRYPOINT ["agent-client"]
CMD ["--help"]
