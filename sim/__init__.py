"""A 2D multi-robot simulator: Gazebo worlds, diff drive, LIDAR, tag camera, ground truth.

- ``sim.loader.load_world(path)`` → ``sim.world.World`` (SDF via ``sim.sdf``, nav2 maps via
  ``sim.mapworld``); ``sim.grid.rasterise`` turns a world into a nav2 grid.
- ``sim.raycast.RayCaster`` casts LIDAR beams; ``sim.robot`` and ``sim.odometry`` move robots
  and make their odometry drift; ``sim.camera`` decides which tags are seen and renders them.
- ``sim.simulator.Simulator`` steps it all without I/O; ``sim.process.run`` puts it on the bus
  (``mrslam sim``); ``sim.world_map.run`` is ``mrslam world-map``.
"""
