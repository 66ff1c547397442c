"""sim_world: a pymunk world of differential-drive robots with lidar and occlusions.

The package exports nothing itself; its modules are the API:

    sim_world.config     SimConfig: what a run is set up with
    sim_world.service    SimService, open_service: the simulator on the fabric
    sim_world.sim        Simulation, ScanEvent: the simulation in lockstep, in code
    sim_world.world      WorldSpec, load_world, find_world, check_world: world files
    sim_world.viz        RerunLog: Rerun recordings
    sim_world.geometry, .physics, .occlusion, .kinematics, .navigation, .executor
    sim_world.schema     the JSON Schema of world files (``python -m sim_world.schema``)

``python -m sim_world --help`` runs it on its own Zenoh session.
"""

__all__: list[str] = []
