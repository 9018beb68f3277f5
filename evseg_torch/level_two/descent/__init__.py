"""Level two's descent: the segmenter that drives it, the steps and the one function that decides the
next, each window's state, and the helpers that batch windows and time their stages."""
