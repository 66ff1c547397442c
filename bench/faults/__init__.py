"""Fault injection into the lidar-occlusion loop under ``rap up``: ``python -m
bench.faults`` (``make faults``); see bench/faults/__main__.py and docs/reliability.md."""
