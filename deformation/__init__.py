"""Kinematics, skinning, splines, pose-space interpolation and resampling.

The lowest package: it imports from no other package of the workbench.
"""
