"""Stand-ins for the robot's serial devices, on pseudo-terminals: an RPLIDAR A2 (``rplidar``) and
the base's microcontroller (``base``). Each speaks the real protocol of its device (the encoders
of ``rplidar_protocol`` and ``base_protocol``), so the agent's hardware backend runs unchanged
against them: in tests, in ``bench/agent.py``, or on a desktop without the robot (POSIX only)."""
