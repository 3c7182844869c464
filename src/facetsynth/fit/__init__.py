"""The fit, one module per step of paper 002: separation, shading normals and light factors, push-pull, sharpness,
partial NDFs, clustering, synthesis, the remaining parameters, and refine.
"""
