"""evaluation package, by job (each subpackage imports only those listed before it;
tests/test_import_layers.py):

* :mod:`evaluation.metrics`: what a run is measured by (pose accuracy and the success
  criteria, Sim(3) alignment, image metrics, floaters);
* :mod:`evaluation.initialisers`: the initialisers beside VGGT and the baselines (COLMAP,
  posed, oracle, random points, bundle adjustment), each a ``python -m`` stage command;
* :mod:`evaluation.reports`: a results tree read into tables, plots and the HTML report;
* :mod:`evaluation.study`: the initialisation study (its grid of cells and its report).

``python -m evaluation <command>`` (:mod:`evaluation.__main__`) is the CLI of the metrics,
the reports and the study.
"""

from runtime.stops import early_if_main as _early

_early()  # first: a stop while `python -m` loads the command is one line, exit 128 + the signal
