"""The GPU check's report as a Markdown table: :func:`format_gpu_table`.

Read by ``python -m benchmarks --gpu`` (``benchmarks/gpu_check.py``), which prints it beside its
JSON, and by the results page (:mod:`experiments.results_doc`), which renders the GPU records of
``benchmarks/records/`` with it. Here, with the page, so that the studies import nothing from the
benchmarks above them.
"""

from __future__ import annotations

__all__ = ["PARTS", "format_gpu_table"]

# The GPU check's parts, in the order it runs them and the table lists them
PARTS = ("vggt_fixtures", "vggt_chunked", "vggt_cli", "vggt_speed", "gsplat_build", "rasterizer_parity", "rasterizer_timing", "workflow_cell",
         "profile", "profile_late", "step_ab", "cell", "native", "cell_sparse", "loop_gap", "vggt_frames", "vggt_many",
         "backend_agree", "vggt_search")


def _f(x, spec: str = ".3g") -> str:
    return "n/a" if x is None else format(x, spec)


def _cell_rows(c: dict, label: str) -> list[tuple[str, str]]:
    tr = c["train"]
    return [(f"{label}: {c.get('scene')} n={c.get('n')}, {c.get('iterations')} it, recipe {tr.get('recipe')}",
             f"{tr.get('rasterizer')} on {tr.get('device')}"),
            (f"{label}: train s (it/s)", f"{_f(tr.get('wall_s'), '.1f')} ({_f(tr.get('it_per_s'), '.1f')})"),
            (f"{label}: peak GPU MB (training)", _f(tr.get("peak_cuda_mb"), ".0f")),
            (f"{label}: Gaussians, held-out PSNR / SSIM / LPIPS-vgg",
             f"{tr.get('final_gaussians')}, {_f(c['metrics'].get('psnr'), '.2f')} / "
             f"{_f(c['metrics'].get('ssim'), '.3f')} / {_f(c['metrics'].get('lpips_vgg'), '.3f')}"),
            (f"{label}: total s (train + render + metrics; CPU stages elsewhere)",
             _f(sum(c["stages_s"].get(k, 0.0) for k in ("train", "render", "metrics")), ".1f"))]


def _all_records_text(a: dict | None) -> str:
    if not a:
        return ""
    hw = "" if a.get("psnr_diff_hw95") is None else f" ± {_f(a['psnr_diff_hw95'], '.2f')}"
    return f"; against all {a['seeds']} CPU records ({_f(a['mean'], '.2f')} dB): {_f(a['psnr_diff'], '+.2f')}{hw} (Welch)"


def format_gpu_table(r: dict) -> str:
    """The report as a Markdown table (one row per measured number)."""
    rows = [("device", r.get("device")), ("torch / CUDA / gsplat", f"{r.get('torch')} / {r.get('cuda')} / {r.get('gsplat')}")]
    b = r.get("gsplat_build", {})
    if "load_or_build_s" in b:
        rows.append((f"gsplat CUDA extension JIT build (arch {b.get('arch_list')}, MAX_JOBS {b.get('max_jobs')}), s",
                     _f(b["load_or_build_s"], ".0f")))
    v = r.get("vggt_fixtures", {})
    for tf in ("tf32_off", "tf32_on"):
        for dt in ("float64", "float32"):
            if dt in v.get(tf, {}):
                rows.append((f"VGGT fixtures on CUDA, {dt}, {tf.replace('_', ' ')}: max abs err vs {dt} expectation",
                             _f(v[tf][dt]["max"])))
    vc = r.get("vggt_chunked", {})
    for dt in ("float64", "float32"):
        if dt in vc:
            rows.append((f"VGGT fixtures on CUDA, every chunked path forced on, {dt}, TF32 off: max abs err",
                         _f(vc[dt]["max"])))
    for part in ("vggt_frames", "vggt_many", "vggt_search"):
        vf = r.get(part, {})
        for rec in vf.get("real", []):
            if rec.get("peak_mb") is not None:
                rows.append((f"VGGT-1B {rec['frames']} frames {vf.get('size')} bf16, random weights: s, s per frame, "
                             "peak MB", f"{_f(rec.get('wall_s'))}, {_f(rec.get('s_per_frame'))}, "
                                        f"{_f(rec.get('peak_mb'), '.0f')}"))
        search = vf.get("search", {})
        if search.get("largest_fit_frames"):
            rows.append(("VGGT-1B largest frame count that fits (memory probe), its peak MB; upstream",
                         f"{search['largest_fit_frames']}, {_f(search.get('largest_fit_peak_mb'), '.0f')}; "
                         f"{vf.get('upstream', {}).get('frames')} on {vf.get('upstream', {}).get('memory_gb')} GB"))
    ba = r.get("backend_agree", {})
    for recipe, b in ba.get("by_recipe", {}).items():
        hw = "" if b.get("psnr_diff_hw95") is None else f" ± {_f(b['psnr_diff_hw95'], '.2f')}"
        rows.append((f"{ba.get('rasterizer')} vs the grid's CPU records, {ba.get('cell')} {ba.get('iterations')} it, "
                     f"{recipe}, seeds {b['seeds']}: final held-out PSNR",
                     f"{_f(b['this_psnr'], '.2f')} vs {_f(b['record_psnr'], '.2f')} dB, "
                     f"diff {_f(b['psnr_diff'], '+.2f')}{hw}" + _all_records_text(b.get("all_records"))))
    vs = r.get("vggt_speed", {})
    if "bf16" in vs:
        rows.append((f"VGGT-1B forward, {vs['frames']} views {vs['size']}, camera + point heads, random weights: "
                     "fp32 / bf16 s (peak GPU MB)",
                     f"{_f(vs['fp32']['forward_s_median'])} / {_f(vs['bf16']['forward_s_median'])} "
                     f"({_f(vs['fp32']['peak_gpu_mb'], '.0f')} / {_f(vs['bf16']['peak_gpu_mb'], '.0f')})"))
    p = r.get("rasterizer_parity", {})
    if "rgb_max_abs_diff" in p:
        rows.append(("torch vs gsplat: rgb max / mean abs diff",
                     f"{_f(p.get('rgb_max_abs_diff'))} / {_f(p.get('rgb_mean_abs_diff'))}"))
        for k in ("means", "quats", "scales", "opacities", "sh", "means2d_grad"):
            rows.append((f"torch vs gsplat: grad rel L2, {k}", _f(p.get(f"grad_rel_l2_{k}"))))
        rows.append(("means2d grad shape (torch, gsplat)",
                     f"{p.get('torch_means2d_grad_shape')}, {p.get('gsplat_means2d_grad_shape')}"))
    t = r.get("rasterizer_timing", {})
    if "torch" in t:
        rows.append((f"fwd+bwd ms torch / gsplat ({t.get('case')})",
                     f"{_f(t['torch']['fwd_bwd_ms'])} / {_f(t['gsplat']['fwd_bwd_ms'])} "
                     f"(x{_f(t.get('speedup_gsplat'))})"))
        rows.append(("peak GPU MB torch / gsplat", f"{_f(t['torch']['peak_gpu_mb'], '.0f')} / "
                                                   f"{_f(t['gsplat']['peak_gpu_mb'], '.0f')}"))
    w = r.get("workflow_cell", {})
    if "device_run" in w:
        d, c = w["device_run"], w["cpu_run"]
        rows.append((f"workflow cell {w['cell']} ({c['train'].get('config', {}).get('iterations')} it), held-out "
                     "PSNR / SSIM: CUDA vs CPU",
                     f"{_f(d['metrics']['psnr'], '.2f')} / {_f(d['metrics']['ssim'], '.3f')} vs "
                     f"{_f(c['metrics']['psnr'], '.2f')} / {_f(c['metrics']['ssim'], '.3f')} "
                     f"(diff {_f(w.get('psnr_device_minus_cpu'), '+.2f')} dB)"))
        rows.append(("workflow cell: Gaussians, train s: CUDA vs CPU",
                     f"{d['train']['num_gaussians']}, {_f(d['train']['wall_time_s'], '.1f')} vs "
                     f"{c['train']['num_gaussians']}, {_f(c['train']['wall_time_s'], '.1f')}"))
    g = r.get("vggt_cli", {})
    if "max_abs_diff_vs_cpu" in g:
        rows.append(("vggt_init CLI, fixture model, CUDA vs CPU: max abs diff (world_points, cam_from_world)",
                     f"{_f(g['max_abs_diff_vs_cpu'].get('world_points'))}, "
                     f"{_f(g['max_abs_diff_vs_cpu'].get('cam_from_world'))}"))
    for recipe, pr in r.get("profile", {}).items():
        if not isinstance(pr, dict) or "graphs_on" not in pr:
            continue
        tp = pr["torch_profiler"]
        rows.append((f"step profile, {recipe}, it {pr['warm_iterations']}+{pr['steps']} "
                     f"({pr['graphs_on']['gaussians']} Gaussians): ms per iteration, loss graphed / op by op",
                     f"{_f(pr['graphs_on']['ms_per_step'])} / {_f(pr['graphs_off']['ms_per_step'])}"))
        rows.append((f"step profile, {recipe}: device busy ms, kernel launches, syncs, copies per iteration",
                     f"{_f(tp['device_busy_ms_per_it'])}, {_f(tp['kernel_launches_per_it'], '.0f')}, "
                     f"{_f(tp['syncs_per_it'], '.2g')}, {_f(tp['memcpy_per_it'], '.2g')}"))
        rows.append((f"step profile, {recipe}: gsplat forward + backward alone, ms", _f(pr["rasterizer_only_ms"])))
        ph = pr["phases"]["host_ms"]
        rows.append((f"step profile, {recipe}: host ms per phase",
                     ", ".join(f"{k} {_f(v, '.2f')}" for k, v in ph.items())))
    for recipe, pl in r.get("profile_late", {}).items():
        if not isinstance(pl, dict) or "median_ms" not in pl:
            continue
        m, fp = pl["median_ms"], pl["footprint"]
        rows.append((f"late step, {recipe}, after {pl['warm_iterations']} it ({pl['gaussians']} Gaussians): ms per "
                     "iteration, statistics skipped / computed; gsplat alone",
                     f"{_f(m['stats_skipped'])} / {_f(m['stats_computed'])}; {_f(pl['rasterizer_only_ms'])}"))
        if "torch_profiler" in pl:
            rows.append((f"late step, {recipe}: device busy ms per iteration; tile intersections (per visible "
                         "Gaussian)", f"{_f(pl['torch_profiler']['device_busy_ms_per_it'])}; "
                                      f"{fp['tile_intersections']} ({_f(fp['tiles_per_visible'])})"))
    ab = r.get("step_ab", {})
    if "sparse" in ab:
        rows.append(("step A/B in one process (" + ", ".join(k for k in ab if k != "setup" and "error" not in k)
                     + "): median ms per iteration",
                     ", ".join(_f(v["median_ms"]) for k, v in ab.items() if isinstance(v, dict) and "median_ms" in v)))
    c = r.get("cell", {})
    if "train" in c:
        rows += _cell_rows(c, "cell")
    nat = r.get("native", {})
    if "wall_s" in nat and "error" not in nat:
        rows.append((f"gsplat-native loop, same cell, {nat['iterations']} it: train s, s / 1000 it",
                     f"{_f(nat['wall_s'], '.1f')}, {_f(nat['s_per_1000_it'], '.2f')}"))
        rows.append(("gsplat-native: Gaussians, held-out PSNR (trainer's), peak GPU MB",
                     f"{nat['final_gaussians']}, {_f(nat['test_psnr'], '.2f')}, {_f(nat['peak_cuda_mb'], '.0f')}"))
        if "train" in c and c["train"].get("wall_s"):
            rows.append(("ours / gsplat-native training time", _f(c["train"]["wall_s"] / nat["wall_s"], ".2f")))
    gap = r.get("loop_gap", {}).get("summary", {})
    if "ours" in gap or "native" in gap:
        rows.append((f"`paper` and gsplat's own loop over seeds, {r['loop_gap']['iterations']} it, "
                     f"{r['loop_gap']['jobs']} runs at a time: held-out PSNR mean (sd, seeds)",
                     "; ".join(f"{k} {_f(v['psnr'], '.2f')} ({_f(v['psnr_sd'], '.2f')}, {len(v['seeds'])})"
                               for k, v in gap.items() if k in ("ours", "native"))))
        d = gap.get("ours_minus_native")
        if d:
            rows.append(("ours - gsplat's own loop, held-out PSNR (Welch 95 %)",
                         f"{d['psnr']:+.2f} ± {_f(d['hw95'], '.2f')} dB"))
    cs = r.get("cell_sparse", {})
    if "train" in cs:
        rows += _cell_rows(cs, "cell, sparse")
    for name in PARTS:
        if "error" in r.get(name, {}):
            rows.append((f"{name}: FAILED", r[name]["error"].strip().splitlines()[-1][:120]))
    lines = ["| check | result |", "|---|---|"] + [f"| {a} | {b} |" for a, b in rows]
    return "\n".join(lines)


