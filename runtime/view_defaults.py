"""Where ``python -m splat_train view`` listens unless told otherwise: one place for the viewer
(splat_train/view) and the report that prints its commands (evaluation/reports/report_view.py).
It lives on the ground floor, not beside the viewer, because stages do not import each other."""

VIEW_HOST = "127.0.0.1"  # this machine only
VIEW_PORT = 8765
