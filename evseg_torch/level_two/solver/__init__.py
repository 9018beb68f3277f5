"""Fitting motions by contrast maximisation: batched L-BFGS and Adam over tiny parameter vectors
(:mod:`.optimizers`), every cluster's fit as one batched problem (:mod:`.cmax`), in crops around small
clusters (:mod:`.crops`)."""
