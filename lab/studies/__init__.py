"""Studies: simulated experiments whose results docs/results.md reports (they return data)."""
