"""Recording runs to MCAP files and replaying them onto the bus."""
