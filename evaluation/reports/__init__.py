"""A results tree read into one record per run (:mod:`.results`, :mod:`.run_status`), and the
tables, plots and HTML report made from it (:mod:`.tables`, :mod:`.plots`, :mod:`.report`,
:mod:`.report_view`)."""
