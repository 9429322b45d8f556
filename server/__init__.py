"""The central daemon: per-robot SLAM, team graphs and merging, exploration, planning, control."""
