"""Image formation: events warped by a motion, splatted by bilinear voting and blurred by a Gaussian, and
the variance of such images with its gradient."""
