"""Sensor plugins: real DIGIT, replay, simulated DIGIT."""
