"""Readers for the real dataset formats under $DS3D_DATA (see ds3d.paths.data_root)."""
