"""Wiring: scenarios, the HIL loop over a bus, recording, viewing, replay and the command line."""
