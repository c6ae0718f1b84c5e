"""Dense multi-view stereo from posed views on the CPU (the ``mvs`` initialiser).

:mod:`.sweep` (plane sweep with NCC), :mod:`.bounds` (which depths and plane directions to
sweep), :mod:`.fusion` (geometric consistency and fusion), :mod:`.run` (the initialiser and
its values), :mod:`.accuracy` (its depth against ground truth and on held-out views);
``python -m evaluation.initialisers.mvs --help`` runs it.
"""
