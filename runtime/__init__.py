"""tactile.runtime"""
