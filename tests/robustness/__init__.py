"""Reliability: bad inputs, injected faults, properties and security, each asserted (README, "Reliability")."""
