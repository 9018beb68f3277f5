"""Fitting motions by contrast maximisation: batched L-BFGS and Adam over tiny parameter vectors, every
cluster's fit as one batched problem, in crops around small clusters."""
