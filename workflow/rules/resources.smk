"""Cluster resources of every rule, from the config (defaults in the schema): memory and
runtime, CPUs per task equal to the rule's threads, and a GPU only where the configured device
is CUDA. They live in the rules, not in a profile, so that a profile or a command line that
sets ``--default-resources`` / ``--set-resources`` (account, partition) never drops them.

Scaling (a retry, ``attempt`` 2, gets twice the memory and time):

    VGGT      mem_mb, runtime  x max(1, n (s/S)^2 / 12)      n views, s the network input width,
                                                             S its default (vggt_init.defaults)
    training  mem_mb           x max(1, n / 12)
              runtime          x max(1, n / 12) x iterations / 10000
"""

import math


def cpus_per_task(wildcards, threads):
    """SLURM CPUs of a job: its threads (the plugin's --cpus-per-task)."""
    return threads


def short_runtime(wildcards, attempt):
    """Minutes of every small job (resources.runtime), doubled on a retry."""
    return config["resources"]["runtime"] * attempt


def _vggt_work(wildcards):
    """The VGGT job's work relative to the one vggt.mem_mb and vggt.runtime are set for: 12
    views at the default network input width (vggt_init.defaults.IMAGE_SIZE)."""
    from vggt_init.defaults import IMAGE_SIZE

    size = config["vggt"]["image_size"] or IMAGE_SIZE
    return max(1.0, int(wildcards.n) * (size / IMAGE_SIZE) ** 2 / 12)


def vggt_mem_mb(wildcards, attempt):
    return math.ceil(config["vggt"]["mem_mb"] * _vggt_work(wildcards) * attempt)


def vggt_runtime(wildcards, attempt):
    return math.ceil(config["vggt"]["runtime"] * _vggt_work(wildcards) * attempt)


def vggt_gpus(wildcards):
    return 1 if config["vggt"]["device"].startswith("cuda") else 0


def train_mem_mb(wildcards, attempt):
    return math.ceil(
        config["train"]["mem_mb"] * max(1.0, int(wildcards.n) / 12) * attempt
    )


def train_iterations():
    """train.iterations, or the trainer's default for the configured device when null."""
    from splat_train.config import default_iterations

    t = config["train"]
    return t["iterations"] or default_iterations(t["device"])


def train_runtime(wildcards, attempt):
    t = config["train"]
    scale = max(1.0, int(wildcards.n) / 12) * train_iterations() / 10000
    return (
        max(config["resources"]["runtime"], math.ceil(t["runtime"] * scale)) * attempt
    )


def train_gpus(wildcards):
    return 1 if config["train"]["device"].startswith("cuda") else 0


def colmap_mem_mb(wildcards, attempt):
    return config["colmap"]["mem_mb"] * attempt


def colmap_runtime(wildcards, attempt):
    return config["colmap"]["runtime"] * attempt
