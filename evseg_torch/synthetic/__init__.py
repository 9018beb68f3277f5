"""Synthetic event scenes with exact ground truth.

* :mod:`~evseg_torch.synthetic.scenes`: :func:`make_scene`, an ESIM-like generator of textured layers
  moved by the motion models, and the :class:`SyntheticScene` it returns;
* :mod:`~evseg_torch.synthetic.families`: named families of seeded scenes
  (:func:`~evseg_torch.synthetic.families.make_family_scene`), such as ``hard``, the failure modes we
  know of.

The scenes' public names are importable from here.
"""

from evseg_torch.synthetic.scenes import LayerMotion, SyntheticScene, make_scene

__all__ = ["LayerMotion", "SyntheticScene", "make_scene"]
