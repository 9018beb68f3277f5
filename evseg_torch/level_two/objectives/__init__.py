"""Contrast objectives and losses of images of warped events: one motion per cluster (:mod:`.contrast`),
or soft assignments to several (:mod:`.multi_model`). Losses are minimised: each is a negative contrast."""
