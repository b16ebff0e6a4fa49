"""tactile.training"""
