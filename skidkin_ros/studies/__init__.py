"""Studies: simulated experiments whose results the README reports (they return data)."""
