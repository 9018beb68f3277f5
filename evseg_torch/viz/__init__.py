"""Pictures of segmentations: RGB images, the paper's Fig. 1 panels, matplotlib figures and video.

* :mod:`~evseg_torch.viz.render`: colours of ids and images of events and labels (NumPy);
* :mod:`~evseg_torch.viz.panels`: one window's Fig. 1 panels as one RGB image (NumPy and OpenCV), and
  PNG writing;
* :mod:`~evseg_torch.viz.figures`: the same panels, and grids of windows with boxes, as matplotlib
  figures (the ``viz`` extra);
* :mod:`~evseg_torch.viz.video`: H.264 video of a recording's windows (the ``video`` extra).

Each module imports only those listed before it.
"""
