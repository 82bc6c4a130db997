"""SARAH data toolkit: Embody-3D-style dyadic captures to training shards."""

__version__ = "0.1.0"
