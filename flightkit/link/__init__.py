"""flightkit.link"""
