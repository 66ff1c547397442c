"""Fleet: many robots' five-stage loops at once on one machine (``python -m bench.fleet``)."""
