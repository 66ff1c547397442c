"""The lidar-occlusion case study as RAP MAPLE-K nodes."""
