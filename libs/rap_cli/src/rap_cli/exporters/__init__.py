"""Exporters: a RAP system model written in a design language (AADL)."""
