"""ds3d.evaluation"""
