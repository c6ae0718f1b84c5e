"""runtime: what every command of the project shares while it runs, none of it camera I/O.

* :mod:`runtime.cliargs`: flag spellings and helpers shared by the command lines;
* :mod:`runtime.logs`: logging, timing and progress bars of the CLIs;
* :mod:`runtime.stops`: SIGTERM, SIGINT and SIGHUP end a command through one exception (one
  line, exit code 128 + the signal), also after pycolmap installed its own handler;
* :mod:`runtime.memory`: glibc's malloc settings that keep freed memory in the process
  (``RETAIN_FREED_MEMORY=0`` turns them off);
* :mod:`runtime.cbuild`: the cached build of single-file C++ kernels loaded with ctypes;
* :mod:`runtime.outdir`: the output rule of every stage and the run of a stage command
  (``prepare_out``, ``seal_out``, ``run_stage``); its parts, lowest first:
  :mod:`runtime.ledger` (the rule's own files: markers, the ledger of what a stage wrote,
  stamps and records), :mod:`runtime.outlock` (the lock of an output folder),
  :mod:`runtime.outcheck` (the refusals of an ``--out``) and :mod:`runtime.outrun` (what a run
  records as it writes; reruns that remove only their own files);
* :mod:`runtime.atomic`: writes that land whole or not at all (temporary file, fsync, rename);
* :mod:`runtime.names`: the rule for names read from files before they become paths;
* :mod:`runtime.view_defaults`: where the browser viewer listens, read by the viewer and by the
  report that prints its commands.

Ground floor, lowest of all (tests/test_import_layers.py): it imports no other package of the
project.
"""
