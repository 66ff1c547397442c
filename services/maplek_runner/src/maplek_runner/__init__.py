"""Hosts the MAPLE-K components that a deployment plan maps to one compute node."""
