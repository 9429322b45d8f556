"""The fleet the server serves: its robots and teams (model), what happens to them (events),
how far their exploration has come (progress), how each robot's parts are built from the
configuration (stages), and how a team's robots share out their targets (coordination)."""
