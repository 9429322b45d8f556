"""The agent on each robot: drivers (or the sim backend), scans and tags out, cmd_vel in."""
