"""Write bench/RESULTS.md: the current numbers of the `fast` preset first, each table from the
JSON reports it names (numbers are never typed), then the experiments of bench/experiments.toml,
one table per question, each row set against the row above it of the same scene and views.

Reports live in bench/reports/current (the measurements of the preset and service as they are
now) and bench/reports/history (everything measured before, kept as measured). A new measurement
of today's preset is written to current/ and replaces its entry below; the one it replaces moves to
history/.

Usage: python bench/results.py  (from the repository root)
"""

from __future__ import annotations

import json
import statistics
import tomllib
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPORTS = HERE / "reports"

# The current report of each kind (in reports/current).
SCENE_REPORTS = {s: f"entsched_test_{s}.json" for s in ("fern", "room", "trex")}
VAL_REPORTS = {s: f"entsched_val_{s}.json" for s in ("fern", "room", "trex")}
SYNTHETIC_REPORT = "entsched_synthetic.json"
POSE_REPORTS = [  # (scene, report): a scene may have a row per kind of photo
    ("fern", "poses_e2e_fern_entsched.json"),
    ("room", "poses_e2e_room_entsched.json"),
    ("room", "poses_e2e_room_exif_entsched.json"),
    ("trex", "poses_e2e_trex_exif_entsched.json"),
]
POSE_ACCURACY_REPORT = "pose_accuracy_peak.json"
POSE_ACCURACY_ENLARGED_REPORT = "pose_accuracy_1600_after.json"
PROFILE_REPORT = "profile_job_fern_cpu_b73079f.json"
PROFILE_SLOWER_REPORT = "profile_job_fern_cpu_54fa497.json"  # the same step cost on a slower machine
# The preset of 2026-12-02 (a245170), profiled twice:
PROFILE_EARLIER_REPORT = "profile_job_fern_cpu_a245170_s37.json"  # on PROFILE_SLOWER_REPORT's machine, alternating
PROFILE_EARLIER_DAY_REPORT = "profile_job_fern_cpu_a245170.json"  # on its own day's machine
PREVIEW_REPORT = "preview_quality_fern_refresh.json"
# e74aa6c's preset on 2026-12-08's faster machine (AMD EPYC, 2 threads): two profiles and a job timeline.
PROFILE_FAST_MACHINE_REPORTS = (
    "profile_job_fern_cpu_e74aa6c_epyc_r2.json",
    "profile_job_fern_cpu_e74aa6c_epyc_r3.json",
)
TIMELINE_FAST_MACHINE_REPORT = "job_timeline_fern_cpu_epyc.json"
TIMELINE_REPORT = "job_timeline_fern_cpu_entsched.json"
TIMELINE_PAIR_REPORT = "job_timeline_fern_cpu_entsched_pair.json"  # the same code, started seven minutes earlier
BUILD_REPORT = "model_build_time_fern_fused.json"
RENDER_REPORT = "render_speed_bicubic_min.json"
SERVICE_REPORT = "service_cpu.json"
DEPLOYMENT_REPORT = "deployment_test.json"
# Issue 38's targets on the test views: PSNR / SSIM / LPIPS-vgg (None: no target).
TARGETS = {"fern": (23.8, 0.78, 0.17), "room": (21.40 + 1.5, None, 0.25), "trex": (20.24 + 1.5, None, 0.25)}
PAGES = [
    ("PRESET_HISTORY.md", "why each setting of `fast` is what it is, oldest first"),
    ("EXPLORE.md", "variants of `fast` on the validation views of fern, room and trex (lent GPU)"),
    ("PROFILE.md", "where the time of one job goes, stage by stage, on the CPU and a GPU; speed changes tried"),
    ("DIAGNOSIS.md", "where views go wrong and what was tried against it"),
    ("poses_e2e.md", "how the estimated-pose runs are registered and scored"),
    ("job_timeline.md", "the whole job through `cmc serve`, run by run"),
    ("preview_quality.md", "how good a preview is after how much training"),
    (
        "reports/history/RESULTS-until-2026-11-27.md",
        "every earlier measurement (serving, service, load, poses, ablations), as measured, with commands",
    ),
]


def find(name: str) -> Path:
    """The report ``name`` in reports/current, else in reports/history."""
    for folder in ("current", "history"):
        if (REPORTS / folder / name).exists():
            return REPORTS / folder / name
    raise FileNotFoundError(f"no report {name} in {REPORTS}/current or history")


def load(name: str) -> dict[str, Any] | None:
    path = REPORTS / "current" / name
    return json.loads(path.read_text()) if path.exists() else None


def source(report: dict[str, Any], name: str) -> str:
    commit = report.get("git_commit") or report.get("commit", "?")
    return f"`{name}` ({commit}, {str(report.get('date', '?'))[:10]})"


def triple(m: dict[str, Any]) -> str:
    return f"{m['psnr']:.2f} / {m['ssim']:.3f} / {m['lpips_vgg']:.3f}"


def view_quality() -> list[str]:
    out = [
        "## View quality of `fast` on the real scenes (test views)",
        "",
        "RegNeRF's 3-view protocol at 504x378 (every 8th image tested, 3 training views evenly from the",
        "rest), baked renderer, 2-core CPU. `CMC_LPIPS_DIR=../shared/weights cmc bench llff --data",
        "../shared/datasets/llff --scenes S --views test --out bench/reports/current/REPORT`; the validation",
        "views (`--views val`: the images neither trained on nor tested, on which settings are chosen) in",
        "the last column. Training seconds depend on the day's machine: the 2-core machines differ by up",
        "to 1.7x (a fern training of the same cost a step took 225 s on one, 350 s on another: bench/PROFILE.md).",
        "",
        "| scene | PSNR / SSIM / LPIPS-vgg | target (issue 38) | met | train s | report | validation views |",
        "|---|---|---|---|---|---|---|",
    ]
    for scene, name in SCENE_REPORTS.items():
        r = load(name)
        if r is None:
            continue
        m = r["mean"]
        t = TARGETS[scene]
        target = " / ".join("-" if v is None else (f">= {v:.2f}" if i < 2 else f"<= {v:.2f}") for i, v in enumerate(t))
        met = all(
            v is None or (m[k] >= v if i < 2 else m[k] <= v)
            for i, (k, v) in enumerate(zip(("psnr", "ssim", "lpips_vgg"), t, strict=True))
        )
        verdict = "yes" if met else "no"
        v = load(VAL_REPORTS[scene])
        val = f"{triple(v['mean'])} ({source(v, VAL_REPORTS[scene])})" if v else "not run"
        row = f"| {scene} | {triple(m)} | {target} | {verdict} | {m['train_seconds']:.0f} | {source(r, name)} | {val} |"
        out.append(row)
    r = load(SYNTHETIC_REPORT)
    if r is not None:
        out += [
            "",
            "The wide-baseline synthetic set (cards, posts, slanted; known depth): `CMC_LPIPS_DIR=../shared/weights",
            f"cmc bench synthetic --out bench/reports/current/REPORT`, {source(r, SYNTHETIC_REPORT)}.",
            "",
            "| views | PSNR / SSIM / LPIPS-vgg | median depth error |",
            "|---|---|---|",
        ]
        for kind in ("near", "halfway", "beyond"):
            m = r["mean"][kind]
            out.append(f"| {kind} | {triple(m)} | {m['depth_rel_error']:.4f} |")
    return out


def poses() -> list[str]:
    out = [
        "## The whole product path: trained from the poses `cmc poses` estimates",
        "",
        "`python bench/poses_e2e.py --data ../shared/datasets/llff/S --steps N --lpips-dir ../shared/weights",
        "--out bench/reports/current/REPORT`: the same pixels trained once with the dataset's poses and once with",
        "the poses SfM estimates from the three training photos, the held-out views registered into the",
        'estimated frame (`poses_e2e.md`). Target (issue 38): within 0.5 dB. The column "after',
        'registering to the model" (`--refine-test-poses model`) registers each held-out photo to each',
        "run's own model with the photo itself: the difference that is the reconstruction's, not the",
        "test views' registration. Registered by: `structure` through the dataset's own sparse model",
        "(fern), `points` by the held-out photo's SIFT matches to the estimated reconstruction's points",
        "(room, trex: no sparse model ships with them). Every row has the preset with the entropy",
        "prior's schedule (a663808). Before it (the view-dependent colour term, `bench/reports/history/`,",
        "`poses_e2e.md`): fern -0.26, room -0.30, room with EXIF -0.42, trex -0.35 dB.",
        "",
        "| scene | photos | steps | dataset poses | estimated poses | PSNR difference | registered by "
        "| after registering to the model | report |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for scene, name in POSE_REPORTS:
        r = load(name)
        if r is None:
            continue
        a = r["runs"]["dataset_poses"]["dataset"]["mean"]
        registration = r.get("registration", "structure")  # reports before the key: structure
        b = r["runs"]["estimated_poses"][registration]["mean"]
        jpeg = r["photos"][0].lower().endswith((".jpg", ".jpeg"))
        photos = "phone JPEGs" if jpeg else "PNGs, EXIF focal" if r.get("exif_focal") else "PNGs, no EXIF"
        model = r.get("difference_after_registration_to_the_model")
        after = f"{model['psnr']:+.2f}" if model else "not run"
        row = (
            f"| {scene} | {photos} | {r['steps']} | {triple(a)} | {triple(b)} | {b['psnr'] - a['psnr']:+.2f} | "
            f"{registration} | {after} | {source(r, name)} |"
        )
        out.append(row)
    return out


def pose_accuracy_table(report: dict[str, Any]) -> list[str]:
    """Markdown rows of a bench/pose_accuracy.py report: one per scene and EXIF case."""
    out = [
        "| scene / EXIF focal | registered | focal error % | rotation error deg | centre error / baseline "
        "| 3D points | seconds |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, entry in report["scenes"].items():
        m = entry["summary"]
        seconds = [t["seconds"] for t in entry["triples"] if "seconds" in t]
        out.append(
            f"| {key} | {m['registered']} | {m['median_abs_focal_error_pct']} | {m['median_rotation_error_deg']} "
            f"| {m['median_centre_error_baseline']} | {m['median_points3D']} "
            f"| {statistics.median(seconds) if seconds else '-'} |"
        )
    return out


def pose_accuracy() -> list[str]:
    r = load(POSE_ACCURACY_REPORT)
    if r is None:
        return []
    out = [
        "## The poses `cmc poses` estimates from three photos, against the dataset's",
        "",
        f"`{r['command']}`, {source(r, POSE_ACCURACY_REPORT)}: SfM on five evenly spaced triples of",
        "each scene's 504x378 photos (with and without the EXIF focal length a phone writes), aligned to",
        "the dataset's cameras by a similarity; medians over the triples of the absolute focal length",
        "error and of the largest rotation and centre error of the three cameras. No training.",
        "",
        *pose_accuracy_table(r),
    ]
    enlarged = load(POSE_ACCURACY_ENLARGED_REPORT)
    if enlarged is not None:
        out += [
            "",
            f"The same triples enlarged to a phone's 1600 px first (`{enlarged['command']}`,",
            f"{source(enlarged, POSE_ACCURACY_ENLARGED_REPORT)}; SIFT at the photo's own scale: no more",
            "detail than 504 px hold, its worst case; before that change: `history/sift_octave.md`):",
            "",
            *pose_accuracy_table(enlarged),
        ]
    return out


def speed() -> list[str]:
    out = ["## Speed: one `fast` job on fern, 2-core CPU", ""]
    r = load(PROFILE_REPORT)
    if r is not None:
        stages = r["stages_s"]
        groups = {
            "model build (plane sweeps)": [k for k in stages if k.startswith("model build")],
            "training": [k for k in stages if k.startswith("train")],
            "preview bake and final bake": ["preview bake", "bake"],
            "load the baked scene, first render": ["load baked scene", "first render"],
        }
        out += [
            "`python bench/profile_job.py --data ../shared/datasets/llff/fern --device cpu`,",
            f"{source(r, PROFILE_REPORT)} (per-stage detail and the GPU column: `PROFILE.md`).",
            "",
            "| stage | seconds | share |",
            "|---|---|---|",
        ]
        for label, keys in groups.items():
            s = sum(stages.get(k, 0.0) for k in keys)
            out.append(f"| {label} | {s:.1f} | {100 * s / r['total_s']:.0f} % |")
        out.append(f"| **total** | **{r['total_s']:.1f}** | |")

        def seconds(report: dict, group: str) -> float:
            return sum(report["stages_s"].get(k, 0.0) for k in groups[group])

        tb = seconds(r, "training") + seconds(r, "preview bake and final bake")
        out += [
            "",
            f"Training and both bakes {tb:.1f} s (issue 39: <= 90 s, {'met' if tb <= 90 else 'not met'} on this"
            " machine).",
        ]
        w, e, d = load(PROFILE_SLOWER_REPORT), load(PROFILE_EARLIER_REPORT), load(PROFILE_EARLIER_DAY_REPORT)
        if w is not None and e is not None and d is not None:
            slow_tb = seconds(w, "training") + seconds(w, "preview bake and final bake")
            day_tb = seconds(d, "training") + seconds(d, "preview bake and final bake")
            out += [
                f"On a slower machine {slow_tb:.1f} s ({source(w, PROFILE_SLOWER_REPORT)}: the preset before the",
                f"entropy prior's schedule, which costs no time); there the preset of {str(d['date'])[:10]}",
                f"({e['git_commit']}, whose training and bakes took {day_tb:.1f} s on that day's faster machine:",
                f"{source(d, PROFILE_EARLIER_DAY_REPORT)}), run alternately ({source(e, PROFILE_EARLIER_REPORT)}):",
                f"training {seconds(e, 'training'):.1f} s, the model build"
                f" {seconds(e, 'model build (plane sweeps)'):.1f} s,",
                f"the job {e['total_s']:.1f} s; fern's test views {e['test_psnr']['bake']:.2f} dB from its final bake"
                f" against {w['test_psnr']['bake']:.2f} dB.",
            ]
    fast = [(name, load(name)) for name in PROFILE_FAST_MACHINE_REPORTS]
    if all(f is not None for _, f in fast):
        out += [
            "On 2026-12-08's faster machine (AMD EPYC, 2 threads), the same code twice, other jobs between",
            f"({', '.join(source(f, name) for name, f in fast)}): training and both bakes",
            " and ".join(f"{seconds(f, 'training') + seconds(f, 'preview bake and final bake'):.1f}" for _, f in fast)
            + " s, the model build "
            + " and ".join(f"{seconds(f, 'model build (plane sweeps)'):.1f}" for _, f in fast)
            + " s, the job "
            + " and ".join(f"{f['total_s']:.1f}" for _, f in fast)
            + " s (`PROFILE.md`, its section of that date).",
        ]
    b = load(BUILD_REPORT)
    if b is not None:
        med = b["median_s"]
        out += [
            "",
            "The model build alone (target <= 10 s), the sweep's torch ops, its compiled kernels"
            f"{' and commit ' + b['command'].split('--before ')[1].split()[0] if 'before' in med else ''}",
            f"alternating, {len(b['seconds']['compiled'])} runs each (`{b['command']}`, {source(b, BUILD_REPORT)}):",
            "median " + ", ".join(f"{k} {v:.1f} s" for k, v in med.items()) + "; the compiled build's parameters",
            f"within {b['compiled_largest_parameter_difference_from']['torch']:.1f} of the torch build's (logits of"
            ' near-tied texels: `PROFILE.md`; the views are the same, table "Speed changes" below)'
            + (
                f", the same as the commit's to the bit: {b['compiled_same_model_to_the_bit_as']['before']}."
                if "before" in med
                else "."
            ),
            "Compare it with the table above only where both name the same machine and commit.",
        ]
    p = load(PREVIEW_REPORT)
    if p is not None:
        # the service's previews (CMC_PREVIEW_AT's default 0, 0.1: steps 0 and 30 of 300)
        first, second = (next(r for r in p["previews"] if r["step"] == step) for step in (0, 30))
        out += [
            "",
            f"The previews a job serves (half the texel resolution): baked at step {first['step']}, test views at",
            f"{first['psnr']:.2f} dB, {first['seconds_from_build_start']:.1f} s after the model build starts",
            "(pose estimation before it: 2.5 s on the phone photos, `history/sift_octave.md`; target: >= 20 dB",
            "within 30 s of the upload),",
            f"then at step {second['step']} {second['psnr']:.2f} dB, "
            f"{second['seconds_from_build_start']:.1f} s after the build starts,",
            f"{source(p, PREVIEW_REPORT)} (`preview_quality.md`; with the planes of c44f8e2 the same",
            "to 0.04 dB at every step, its last section).",
        ]
    t, pair = load(TIMELINE_REPORT), load(TIMELINE_PAIR_REPORT)
    if t is not None and pair is not None:
        out += [
            "",
            "The whole job through `cmc serve`, fern's three phone JPEGs uploaded and polled to `ready`",
            f"(`python bench/job_timeline.py`, {source(t, TIMELINE_REPORT)}, `job_timeline.md`; targets: preview",
            '<= 30 s, ready <= 120 s, ETA within 25 % from 10 % of the job on; "earlier jobs": the jobs the same',
            "`cmc serve` data folder had finished, whose measured pace a job's first estimate takes):",
            "",
            "| steps | earlier jobs | previews after s (their steps) | ready after s | first ETA's error "
            "| ETA within 25 % of the polls |",
            "|---|---|---|---|---|---|",
        ]
        for r in t["runs"]:
            e = r["eta_relative_error"]
            share = f"{100 * e['share_within_25_percent']:.0f} % (median error {100 * e['median']:.0f} %)"
            first = f"{100 * r['first_eta_error']:.0f} %" if "first_eta_error" in r else "-"
            steps = r.get("seconds_to_previews") or {}
            previews = ", ".join(f"{t} ({step})" for step, t in steps.items()) or str(r["seconds_to_preview"])
            out.append(
                f"| {r['steps']} | {r.get('earlier_jobs', '-')} | {previews} | {r['seconds_to_ready']} "
                f"| {first} | {share} |"
            )
        out += [
            "",
            "Seconds depend on the day's machine and drift within it: on the same machine seven minutes",
            f"earlier ({source(pair, TIMELINE_PAIR_REPORT)}) the same code's 300-step jobs were ready after",
            " and ".join(f"{r['seconds_to_ready']}" for r in pair["runs"])
            + ' s (`job_timeline.md`, "The entropy prior\'s schedule, on a faster machine");'
            " earlier presets' after 104-164 s on",
            "other 2-core machines and 204 s on the slowest. A machine's first job with its kernels not yet compiled",
            "(none after `make install` or in the images) has its ETA within 25 % at 83 % of its polls since 0aab94d.",
        ]
    f = load(TIMELINE_FAST_MACHINE_REPORT)
    if f is not None:
        out += [
            "On 2026-12-08's faster machine (AMD EPYC, 2 threads; the same code as the profile above,"
            f" {source(f, TIMELINE_FAST_MACHINE_REPORT)}):",
            " and ".join(f"{r['seconds_to_ready']}" for r in f["runs"])
            + " s to `ready` for "
            + " and ".join(f"{r['steps']}" for r in f["runs"])
            + " steps, the previews after "
            + "; ".join(", ".join(f"{t} s" for t in r["seconds_to_previews"].values()) for r in f["runs"])
            + " (`job_timeline.md`, its section of that date).",
        ]
    return out


def serving() -> list[str]:
    r = load(RENDER_REPORT)
    if r is None:
        return []
    out = [
        "## Serving: a baked fern render (504x378, 3 x 56 planes, compiled CPU renderer)",
        "",
        f"`{r['command']}`, {r['machine']['cpu']} {r['machine']['cores']} cores, {r['date'][:10]}, {r['git_commit']}:",
        f"median {r['overall']['median_ms']:.0f} ms, p90 {r['overall']['p90_ms']:.0f} ms (target 150 ms);",
        f"a loaded scene holds {r['memory']['scene_mb']:.0f} MB (target 200 MB).",
    ]
    if "before" in r:
        b = r["before"]
        agreement = [v["psnr_db"] for v in b["agreement_with_after"]]
        out += [
            f"The renderer before (`{b['rendering']}`) on the same bake, render by render alternating:",
            f"median {b['overall']['median_ms']:.0f} ms, p90 {b['overall']['p90_ms']:.0f} ms; the two renders",
            f"{min(agreement):.0f}-{max(agreement):.0f} dB apart (`PROFILE.md`).",
        ]
    return out


def service() -> list[str]:
    out = []
    r = load(SERVICE_REPORT)
    if r is not None:
        render, up, scene, many = r["render"], r["upload"], r["scene"], r["concurrent"]
        w, h = render["size"]
        out += [
            "## Service: the API on this machine (`cmc serve`'s stack: uvicorn, a Celery worker, Redis)",
            "",
            f"`{r['command']}`, {source(r, SERVICE_REPORT)}: an upload of the three fern JPEGs",
            f"{1000 * up['median_s']:.0f} ms (median of {len(up['seconds'])}), a {scene['steps']}-step scene",
            f"ready in {scene['seconds_to_ready']:.0f} s, a {w}x{h} render through the API p50",
            f"{1000 * render['p50_s']:.0f} ms, p90 {1000 * render['p90_s']:.0f} ms; {many['requests']} renders at",
            f"once: {many['ok']} answered, median {many['median_s']:.1f} s. Renders under load, quotas,",
            "stopping and restarting: the history page below.",
            "",
        ]
    d = load(DEPLOYMENT_REPORT)
    if d is not None:
        m = d["measured"]
        peak = {k: v / 2**20 for k, v in m["peak_memory_bytes"].items()}
        passed = sum(c["ok"] for c in d["checks"])
        stages = ", ".join(f"{k} {v:.0f} s" for k, v in m["job_stages_seconds"].items())
        out += [
            "## Deployment: docker-compose.yml's stack started from its images",
            "",
            f"`{d['command']}` ({d['git_commit']}, {d['date']}, {d['host']}): {passed} of {len(d['checks'])}"
            " checks passed; a",
            f"{d['settings']['short_job']['steps']}-step job at {d['settings']['short_job']['resolution']} px"
            f" {m['job_seconds']:.0f} s ({stages}); first render {m['render_ms']['first']} ms (torch imported and"
            " the scene loaded from the bucket), then",
            f"{m['render_ms']['loaded_median']} ms (median); peak memory of the CPU worker",
            f"{peak['worker-cpu']:.0f} MiB, the API {peak['api']:.0f} MiB.",
        ]
    return out


def _cells(r: dict[str, Any]) -> tuple[str, str, dict[str, Any], str]:
    """(scene, views, the main metrics, the triple cell) of a `cmc bench` report; the synthetic
    set's main metrics are its halfway views'."""
    scene = "+".join(s["scene"] for s in r["scenes"])
    views = r.get("scored_views", "test")
    if "halfway" in r["mean"]:
        views = "synthetic"
        m = r["mean"]["halfway"]
        near, beyond = r["mean"]["near"]["psnr"], r["mean"]["beyond"]["psnr"]
        cell = f"{triple(m)} (halfway); near {near:.2f}, beyond {beyond:.2f} dB"
    else:
        m = r["mean"]
        cell = triple(m)
    if r.get("near_scale", 1.0) != 1.0:
        views += f", near x {r['near_scale']:g}"
    return scene, views, m, cell


def experiments() -> list[str]:
    """One table per question of bench/experiments.toml."""
    questions = tomllib.loads((HERE / "experiments.toml").read_text())["question"]
    out = [
        "## Experiments: one table per question",
        "",
        "From `bench/experiments.toml` (what each run changed and the verdict); each report written by",
        "`CMC_LPIPS_DIR=../shared/weights cmc bench llff --data ../shared/datasets/llff --scenes S --views V",
        "[--near-scale X] [--set KEY=VALUE] --out bench/reports/current/REPORT` (or `cmc bench synthetic`)",
        "on the 2-core CPU. Each row is set against the row above of the same scene and views, or against",
        "the report its `vs` names.",
        "",
    ]
    head = "| scene | views | change | PSNR / SSIM / LPIPS-vgg | vs the row above | verdict | date | report |"
    for q in questions:
        out += [f"### {q['title']}", "", head, "|---|---|---|---|---|---|---|---|"]
        last: dict[tuple[str, str], dict[str, Any]] = {}
        for run in q["runs"]:
            r = json.loads(find(run["report"]).read_text())
            scene, views, m, cell = _cells(r)
            before = _cells(json.loads(find(run["vs"]).read_text()))[2] if "vs" in run else last.get((scene, views))
            delta = (
                f"{m['psnr'] - before['psnr']:+.2f} / {m['ssim'] - before['ssim']:+.3f} / "
                f"{m['lpips_vgg'] - before['lpips_vgg']:+.3f}"
                if before
                else ""
            )
            last[(scene, views)] = m
            cols = [scene, views, run["change"], cell, delta, run["verdict"], str(r["date"])[:10], run["report"]]
            out.append("| " + " | ".join(cols) + " |")
        out.append("")
    return out


def main() -> None:
    out = [
        "# Results: the current numbers, then the experiments",
        "",
        "Generated by `python bench/results.py` from the reports named in each table: those of the",
        "preset and the service as they are now in `bench/reports/current/`, everything measured before",
        "in `bench/reports/history/`, kept as measured. Each number in the first sections is of the",
        "`fast` preset as it is now unless its row says otherwise.",
        "",
    ]
    for section in (view_quality(), poses(), pose_accuracy(), speed(), serving(), service(), experiments()):
        if section:
            out += [*section, ""]
    out += ["## Where the history is", ""]
    out += [f"- `bench/{page}`: {what}" for page, what in PAGES]
    (HERE / "RESULTS.md").write_text("\n".join(out) + "\n")


if __name__ == "__main__":
    main()
