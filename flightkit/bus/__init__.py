"""flightkit.bus"""
