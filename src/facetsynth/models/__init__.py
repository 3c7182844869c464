"""Reflectance models: the paper's microfacet SVBRDF (eqs. 2-6) and its folder, the portable GGX material, the Ward
baseline, and the pixel model (eq. 8 read forwards).
"""
