"""The initialisation study (docs/reference.md section 6): its grid of cells (:mod:`.grid`) and its
report (``python -m evaluation study``): the runs read (:mod:`.collect`), means with 95 %
intervals (:mod:`.stats`), tables (:mod:`.tables`), plots (:mod:`.plots`), and the Markdown and
HTML report written from them (:mod:`.report`)."""
