"""Nonlinear and linear solvers (Newton, CG, sparse host linear algebra)."""
