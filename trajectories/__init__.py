"""trajectories: part of flightkit."""
