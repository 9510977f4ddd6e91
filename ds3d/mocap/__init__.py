"""ds3d.mocap"""
