"""Readers for the real dataset formats under $DS3D_DATA (see ds3d.util.paths.data_root)."""
