"""Captures in: the manifest and its checks, HDR assembly, 8-bit responses and transfer functions, rectification
onto the sample plane.
"""
