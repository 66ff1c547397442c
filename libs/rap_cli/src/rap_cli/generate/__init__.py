"""``rap generate``: a runnable Python package from a system model.

- :mod:`.wiring`: which fabric key each port uses, and the Legitimate/Execute gate;
- :mod:`.messages`: msgspec Structs from the model's messages;
- :mod:`.nodes`: a node module per component, with user regions;
- :mod:`.tests`: a Harness test per component and a whole-loop test;
- :mod:`.deploy_files`: per compute node plan slice, Zenoh configs, compose, Dockerfile;
- :mod:`.package`: all of it written to a folder, keeping the user's regions;
- :mod:`.pyfmt`: the generated Python as ``ruff format`` and ``ruff check`` want it.
"""
