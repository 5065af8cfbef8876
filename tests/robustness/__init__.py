"""Reliability: bad inputs, injected faults, properties and security, each asserted (docs/reliability.md)."""
