"""bench/twin: the lidar case's digital twin (lidar_occlusion.twin) - what a rollout of one
plan period costs, against the simulator over the same 8 s and the twin on an empty map in
the same run, and how far its prediction lands from where the simulator goes."""
