"""Who steps the training servers: the Collector shape and its lock-step, many-ego and
chunked collectors, the sampling workers (in processes or on Ray), the exploration schedule."""
