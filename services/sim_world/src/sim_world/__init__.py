"""sim_world: a pymunk world of differential-drive robots with lidar and occlusions."""
