"""estimation: part of flightkit."""
