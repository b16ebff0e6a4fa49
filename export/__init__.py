"""tactile.export"""
