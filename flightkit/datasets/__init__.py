"""flightkit.datasets"""
