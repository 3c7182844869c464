"""Geometry: the camera, the rectified sample plane, the direction grid, the lights' plane and what the lights
sampled.
"""
