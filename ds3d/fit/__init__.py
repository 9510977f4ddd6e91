"""ds3d.fit"""
