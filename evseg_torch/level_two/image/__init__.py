"""Image formation: events warped by a motion (:mod:`.warp`), splatted by bilinear voting (:mod:`.splat`),
blurred by a Gaussian (:mod:`.blur`), and the variance of such images with its gradient (:mod:`.variance`)."""
