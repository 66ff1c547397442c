"""A module whose import fails, for the loader's error test."""

raise RuntimeError("this module is broken on purpose")
