"""The application layer: what ``evseg`` does with recordings, on top of the segmenter.

* :mod:`~evseg_torch.app.cli`: the ``evseg`` command line, one module per command;
* :mod:`~evseg_torch.app.jobs`: a run's inputs, each with its output folder and options;
* :mod:`~evseg_torch.app.runs`: one recording segmented into a result folder (resumable), and many
  recordings one after another or in worker processes;
* :mod:`~evseg_torch.app.signals`: stopping a run by SIGINT or SIGTERM;
* :mod:`~evseg_torch.app.cluster`: many recordings as tasks on a Dask cluster;
* :mod:`~evseg_torch.app.workers`: a stream's windows shared out among worker processes;
* :mod:`~evseg_torch.app.output` and :mod:`~evseg_torch.app.results`: result folders written and read
  back;
* :mod:`~evseg_torch.app.threads`: the CPU threads of one process.

Nothing in the core (the pipeline, its levels, events, io, evaluation, viz) imports this package.
"""
