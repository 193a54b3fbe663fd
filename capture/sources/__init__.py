"""Capture sources: sim camera, OpenCV (V4L2/video), RealSense, replay, mocap bridge."""
