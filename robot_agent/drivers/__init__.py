"""Hardware drivers of the agent: RPLIDAR, motor base, camera, depth pseudo-scan, camera tower.

Each protocol lives in a pure module (bytes in, numbers out, no I/O) beside the driver that
moves those bytes over a serial port or a capture device, so the protocols can be tested on
byte strings built from their specifications.
"""
