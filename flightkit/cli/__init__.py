"""flightkit.cli"""
