"""Numerical core: plain functions over numpy arrays and frozen dataclasses. Imports neither rclpy nor messages.

Units: millimetres for lengths and displacements, newtons for forces, MPa (N/mm^2) for moduli.
"""
