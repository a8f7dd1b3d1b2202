"""Vox-E core: voxel-grid reconstruction, text-guided editing and localisation.

A plain library (no web, queue or database imports). One module per concept of
the paper; every stage is a function over a typed config whose defaults are the
paper's (see ``../shared/SPEC.md``).
"""

__version__ = "0.1.0"
