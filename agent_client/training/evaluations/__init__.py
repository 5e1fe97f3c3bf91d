"""A training run's evaluations: when they run, what they are judged against, and where they
run (inline on the training servers, or by worker processes on servers of their own)."""
