"""capture: part of flightkit."""
