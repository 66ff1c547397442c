"""The ``rap`` command: RAP's toolkit for system models (check, show, import, export)."""
