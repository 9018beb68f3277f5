"""Level two's descent: the segmenter that drives it (:mod:`.segmenter`), the steps and the one function
that decides the next (:mod:`.steps`), each window's state (:mod:`.state`), and the helpers that batch
windows (:mod:`.batches`, :mod:`.clock`)."""
