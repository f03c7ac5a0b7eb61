"""Render stage: ray samplers and volume rendering as pure functions; the network is passed in."""
