"""flightkit.mocap"""
