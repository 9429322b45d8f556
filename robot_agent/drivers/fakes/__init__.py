"""Stand-ins for the robot's serial devices, on pseudo-terminals: an RPLIDAR A2 (``rplidar``),
the base's microcontroller (``base``) and the camera tower's stepper controller (``tower``).
Each speaks the real protocol of its device (the encoders of ``rplidar_protocol``,
``base_protocol`` and ``tower_protocol``), so the agent's hardware backend runs unchanged
against them: in tests, in ``bench/agent.py``, or on a desktop without the robot (POSIX only)."""
