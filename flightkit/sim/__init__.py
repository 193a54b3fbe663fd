"""flightkit.sim"""
