"""The lidar-occlusion case study as RAP MAPLE-K nodes: :mod:`lidar_occlusion.nodes` (the
five stages), ``python -m lidar_occlusion.demo`` and ``python -m lidar_occlusion.eval``."""

__all__: list[str] = []
