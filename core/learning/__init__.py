"""Learned per-node correction of the FEM replay (Wu et al. 2020, Sec. 3.3, Table 3)."""
