"""ds3d.image2d"""
