"""Helpers the tests share (scenes, files of every format, tolerances); no tests here.

Tests import what they share from this package, never from each other.
"""
