"""CLI: ``python -m vggt_init --images DIR --out DIR [...]`` (parses arguments, calls run())."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from camio.limits import MAX_IMAGE_SIDE
from runtime.checks import flag
from runtime.logs import setup_logging
from vggt_init import defaults

log = logging.getLogger("vggt_init")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m vggt_init",
        description="Run VGGT on a set of images; write predictions.npz, sparse/0 (COLMAP text, original "
                    "resolution) and timing.json into --out.")
    p.add_argument("--images", required=True, type=Path, help="folder with the input images")
    p.add_argument("--image-list", type=Path, help="text file with image names (relative to --images), one per line")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--checkpoint", type=Path,
                   help="model.pt or model.safetensors (else $VGGT_CHECKPOINT, the HF cache, or a download)")
    p.add_argument("--model-config", type=Path,
                   help="JSON architecture in the fixtures' config.json format (default: VGGT-1B)")
    p.add_argument("--dtype", choices=("auto", "fp32", "bf16"),
                   help="bf16 runs the aggregator under autocast; heads stay fp32. Default auto: bf16 on a "
                        "CUDA GPU that supports it, else fp32")
    p.add_argument("--device", help="auto (default: CUDA when available, else CPU), cpu or cuda[:N]")
    p.add_argument("--points-from", choices=defaults.POINT_SOURCES, default=defaults.POINTS_FROM,
                   help="world points from the point head (paper) or depth head + cameras")
    p.add_argument("--max-points", type=flag(int, 1), default=defaults.MAX_POINTS,
                   help="points kept in sparse/0 (most confident)")
    p.add_argument("--mode", choices=defaults.MODES, default=defaults.MODE, help="VGGT preprocessing mode")
    p.add_argument("--image-size", type=flag(int, 14, MAX_IMAGE_SIDE), default=defaults.IMAGE_SIZE,
                   help="network width/longer side (multiple of 14)")
    p.add_argument("--frames-chunk", type=flag(int, 1), default=defaults.FRAMES_CHUNK,
                   help="frames per DPT-head chunk (memory vs speed)")
    p.add_argument("--max-memory-gb", type=flag(float, 0, lo_open=True),
                   help="memory budget (default: what the OS reports free)")
    p.add_argument("--threads", type=flag(int, 0), help="torch CPU threads")
    p.add_argument("--no-retain-memory", action="store_true",
                   help="let glibc return freed memory to the system at once (less peak RSS, slower on CPU; "
                        "see runtime/memory.py)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    from vggt_init.checkpoint import CheckpointFormatError, CheckpointNotFoundError, StateDictMismatchError
    from vggt_init.preprocess import ImageInputError
    from vggt_init.run import MemoryBudgetError, RunOptions, run

    from runtime.outdir import prepare_out, run_stage, typed_line
    from runtime.memory import retain_freed_memory

    def work() -> None:
        prepare_out(args.out, {"--images": args.images, "--image-list": args.image_list,
                               "--checkpoint": args.checkpoint, "--model-config": args.model_config}, "vggt_init")
        if not args.no_retain_memory:
            retain_freed_memory()  # process-wide, so only the CLI does it
        opts = RunOptions(
            images=args.images, out=args.out, image_list=args.image_list, checkpoint=args.checkpoint,
            model_config=args.model_config, points_from=args.points_from, max_points=args.max_points,
            mode=args.mode, image_size=args.image_size,
            frames_chunk_size=args.frames_chunk, max_memory_gb=args.max_memory_gb, threads=args.threads,
            **{k: v for k, v in (("dtype", args.dtype), ("device", args.device)) if v is not None},  # else RunOptions'
        )
        run(opts)

    return run_stage(log, work, errors=(CheckpointNotFoundError, CheckpointFormatError, StateDictMismatchError,
                                        ImageInputError, MemoryBudgetError, FileNotFoundError, ValueError),
                     line=typed_line)


if __name__ == "__main__":
    raise SystemExit(main())
