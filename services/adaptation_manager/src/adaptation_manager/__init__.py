"""RAP adaptation manager: the registry of a running system, its watches and dashboard."""
