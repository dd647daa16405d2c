"""One screen per step of the measurement (thesis figure 9.1)."""
