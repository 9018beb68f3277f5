"""Contrast objectives and losses of images of warped events, of one motion per cluster or of soft
assignments to several. Losses are minimised: each is a negative contrast."""
