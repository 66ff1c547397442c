"""bench/sim: the vectorised raycaster against pymunk per-beam queries, and the
real-time factor of the default world in lockstep."""
