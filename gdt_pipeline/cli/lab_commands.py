"""The lab commands: scene, simulate, eval — the front door to the simulation and evaluation packages.

This is the only engine module that may import them, and only inside the commands, so that the rest of the CLI
works without them."""

from __future__ import annotations

import json
from pathlib import Path

import click

from .common import err_console, installed_registry

SCENES = {"test-scene": "the demo (CAD and one noisy ToF epoch; workflows/demo.yaml)",
          "paper-test-scene": "the paper's four epochs (workflows/test_scene.yaml)",
          "fuselage": "the paper's fuselage section, five brackets added and one removed (workflows/fuselage.yaml)"}


def make_scene(name: str, out_dir: Path, seed: int) -> None:
    """Generate one of the bundled synthetic scenes."""
    if name == "test-scene":
        from ..simulation import make_test_scene

        make_test_scene(out_dir, seed=seed)
    elif name == "paper-test-scene":
        from ..simulation import make_paper_test_scene

        make_paper_test_scene(out_dir, seed=seed)
    else:
        from ..simulation import make_fuselage_scene

        make_fuselage_scene(out_dir, seed=seed)


@click.command()
@click.argument("name", type=click.Choice(list(SCENES)))
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("--seed", default=0, show_default=True, help="Seed of the simulated scans.")
def scene(name: str, out_dir: Path, seed: int) -> None:
    """Generate a synthetic scene (CAD, simulated scans, ground truth) into OUT_DIR.

    test-scene: the demo; paper-test-scene: the paper's four epochs; fuselage: the paper's fuselage section."""
    make_scene(name, out_dir, seed)
    click.echo(f"scene {name!r} written to {out_dir}")


def parse_floats(text: str, n: int, what: str) -> list[float]:
    """``n`` comma-separated numbers of an option (``what`` names it in the error)."""
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        vals = []
    if len(vals) != n:
        raise click.BadParameter(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return vals


def load_meshes(meshes: tuple[Path, ...]) -> list:
    """The meshes to scan, read with trimesh; a clear error for a file that is not a mesh or has no triangles."""
    import trimesh

    loaded = []
    for path in meshes:
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as exc:
            raise click.ClickException(f"{path}: cannot read a mesh: {exc}") from exc
        if not len(getattr(mesh, "faces", [])):
            raise click.ClickException(f"{path}: no triangles to scan")
        loaded.append(mesh)
    return loaded


@click.command()
@click.argument("meshes", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--station", "stations", multiple=True, required=True, metavar="X,Y,Z",
              help="Scanner position (repeat for several scans).")
@click.option("--target", required=True, metavar="X,Y,Z", help="Where the scanners look.")
@click.option("--profile", default="tof_low_cost", show_default=True,
              help="Noise: tof_low_cost, structured_light or a sensor profile YAML.")
@click.option("--kind", type=click.Choice(["pinhole", "spherical"]), default="pinhole", show_default=True)
@click.option("--fov", "fov_deg", default=60.0, show_default=True, help="Field of view (deg).")
@click.option("--density", "points_per_m2", default=20000.0, show_default=True, help="Points per m² at the target.")
@click.option("--max-range", default=10.0, show_default=True, help="Farthest hit kept (m).")
@click.option("--registration-sigma-deg", default=0.0, show_default=True, help="Per-scan rotation error (deg).")
@click.option("--registration-sigma-m", default=0.0, show_default=True, help="Per-scan translation error (m).")
@click.option("--mesh", "as_mesh", is_flag=True, help="Write reconstructed surfaces (Poisson) instead of points.")
@click.option("--seed", default=0, show_default=True)
@click.option("-o", "--out", "out", required=True, type=click.Path(path_type=Path),
              help="Output PLY; with several stations, _s0, _s1 ... are appended.")
def simulate(meshes: tuple[Path, ...], stations: tuple[str, ...], target: str, profile: str, kind: str,
             fov_deg: float, points_per_m2: float, max_range: float, registration_sigma_deg: float,
             registration_sigma_m: float, as_mesh: bool, seed: int, out: Path) -> None:
    """Simulate scans of MESHES (any format trimesh reads) by ray casting, with the sensor's noise.

    Beside each scan go its pose and scanner (<scan>_pose.json) and per-point truth (<scan>_truth.npz: noise-free
    position, object and facet hit, sigmas)."""
    import numpy as np

    from ..sensors import load_profile
    from ..simulation import ScannerSpec, simulate_scan, write_scan

    loaded = load_meshes(meshes)
    try:
        sensor = load_profile(profile, Path.cwd())
    except Exception as exc:
        raise click.ClickException(f"--profile {profile!r}: {exc}") from exc
    spec = ScannerSpec(kind=kind, fov_deg=fov_deg, points_per_m2=points_per_m2, max_range=max_range,
                       profile=sensor.name, registration_sigma_deg=registration_sigma_deg,
                       registration_sigma_m=registration_sigma_m)
    rng = np.random.default_rng(seed)
    aim = np.array(parse_floats(target, 3, "--target"))
    names = [p.stem for p in meshes]
    for k, text in enumerate(stations):
        eye = np.array(parse_floats(text, 3, "--station"))
        scan = simulate_scan(loaded, eye, aim, spec, rng, profile=sensor)
        path = out if len(stations) == 1 else out.with_name(f"{out.stem}_s{k}{out.suffix or '.ply'}")
        written = write_scan(scan, path, object_names=names, spec=spec, as_mesh=as_mesh)
        click.echo(f"{written['scan']}: {len(scan.points)} points from {text} (truth: {written['truth'].name})")


SUITES = ("tof", "precise", "precise-mesh")  # gdt_pipeline.simulation.suite.SUITES, named without importing it


@click.command("eval")
@click.argument("workflow", required=False, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--twin", type=click.Path(path_type=Path), help="Evaluate this existing twin instead of running.")
@click.option("--json", "json_path", type=click.Path(path_type=Path), help="Write the results as JSON here.")
@click.option("--report", "report_dir", type=click.Path(path_type=Path),
              help="Markdown report with plots (default: out/eval/<workflow name>/).")
@click.option("--peers", default="c2c,m3c2,m3c2ep", show_default=True,
              help="Peers to run side by side (comma list of c2c, m3c2, m3c2ep; 'none' for none). With --suite the "
                   "default is c2c,m3c2.")
@click.option("--generate/--no-generate", default=True, show_default=True,
              help="Generate a bundled scene (seed 0) when the workflow's data is missing.")
@click.option("--fusion", type=click.Choice(["most_reliable", "keep_unchanged", "keep_reference", "replace_in_view"]),
              help="Run with this fusion policy instead of the workflow's (twin: <twin>_<fusion>), to compare "
                   "the composites.")
@click.option("--suite", type=click.Choice(SUITES),
              help="Instead of WORKFLOW: generate random scenes of this suite, run each one's default workflow and "
                   "score them all (mean and worst per method).")
# the suites were called scene families until 0.1: earlier notes and scripts say --family
@click.option("--family", "suite_alias", type=click.Choice(SUITES), hidden=True)
@click.option("--scenes", default=20, show_default=True, type=click.IntRange(min=1),
              help="With --suite: how many scenes.")
@click.option("--seed", default=0, show_default=True, type=click.IntRange(min=0),
              help="With --suite: scene k is generated from the seed (SEED, k).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="With --suite: where the scenes and their twins go (default: out/suite/<suite>/).")
@click.pass_context
def eval_cmd(ctx: click.Context, workflow: Path | None, twin: Path | None, json_path: Path | None,
             report_dir: Path | None, peers: str, generate: bool, fusion: str | None, suite: str | None,
             suite_alias: str | None, scenes: int, seed: int, out_dir: Path | None) -> None:
    """Run WORKFLOW on a simulated scene and score every epoch against the scene's ground truth, with the peers.

    With --suite NAME (and no WORKFLOW): score N random scenes of a suite (tof, precise, precise-mesh) the same
    way and report per method the mean and worst change F1, removal recall by visible area and false removals."""
    suite = suite or suite_alias
    if suite is not None:
        if workflow is not None or twin is not None or report_dir is not None or fusion is not None:
            raise click.UsageError("--suite generates its own scenes: give no WORKFLOW, --twin, --report or --fusion")
        default = ctx.get_parameter_source("peers") is click.core.ParameterSource.DEFAULT
        eval_suite(suite, scenes, seed, out_dir, "c2c,m3c2" if default else peers, json_path)
        return
    if workflow is None:
        raise click.UsageError("give a WORKFLOW to evaluate, or --suite NAME to score a suite of random scenes")
    eval_workflow(workflow, twin, json_path, report_dir, peers, generate, fusion)


def parse_peers(peers: str) -> tuple[str, ...]:
    """The --peers list, checked against the known peers."""
    from ..evaluation import PEERS

    chosen = () if peers.strip() == "none" else tuple(p.strip() for p in peers.split(",") if p.strip())
    unknown = [p for p in chosen if p not in PEERS]
    if unknown:
        raise click.BadParameter(f"unknown peers {unknown}; choose from {', '.join(PEERS)}", param_hint="--peers")
    return chosen


def eval_suite(suite: str, scenes: int, seed: int, out_dir: Path | None, peers: str, json_path: Path | None
                ) -> None:
    """``gdt eval --suite``: score the scenes, print the table, write JSON and a markdown table."""
    from ..evaluation.suite import evaluate_suite
    from ..evaluation.suite_report import format_suite_table, suite_markdown

    chosen = parse_peers(peers)
    out = out_dir or Path("out") / "suite" / suite
    err_console.print(f"{scenes} scene(s) of the {suite!r} suite (seed {seed}) into {out} ...")
    def say(msg: str) -> None:
        err_console.print(msg, highlight=False, soft_wrap=True)  # a scene's progress line stays one line

    try:
        result = evaluate_suite(suite, scenes=scenes, seed=seed, out=out, peers=chosen,
                                 registry=installed_registry(), progress=say)
    except FileExistsError as exc:  # --out names a folder that holds something else: refuse, do not delete it
        raise click.ClickException(str(exc)) from exc
    click.echo(format_suite_table(result))
    text = json.dumps(result, indent=2, default=float) + "\n"
    for path in (out / "results.json", json_path):
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
    (out / "results.md").write_text(suite_markdown(result), encoding="utf-8")
    click.echo(f"results written to {json_path or out / 'results.json'}; markdown table: {out / 'results.md'}")


def eval_workflow(workflow: Path, twin: Path | None, json_path: Path | None, report_dir: Path | None, peers: str,
                  generate: bool, fusion: str | None) -> None:
    """``gdt eval WORKFLOW``: run (or read) the twin, score every epoch with the peers, print, write the report."""
    from ..evaluation import evaluate, format_table, missing_scene, with_fusion, write_report

    chosen = parse_peers(peers)
    registry = installed_registry()
    need = missing_scene(workflow, registry)
    if need is not None:
        name, out_dir = need
        if name is None or not generate:
            raise click.ClickException(f"{workflow}: its input data is missing in {out_dir}" +
                                       ("" if name is None else f"; generate it: gdt scene {name} {out_dir}"))
        err_console.print(f"generating the {name} scene into {out_dir} (seed 0) ...")
        make_scene(name, out_dir, 0)
    variant = with_fusion(workflow, fusion) if fusion else None
    try:
        result, arrays = evaluate(variant or workflow, twin=twin, registry=registry, peers=chosen,
                                  progress=lambda m: err_console.print(m))
    finally:
        if variant is not None:
            variant.unlink(missing_ok=True)
    if fusion:
        result["fusion_override"] = fusion
    click.echo(format_table(result))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2, default=float) + "\n", encoding="utf-8")
        click.echo(f"results written to {json_path}")
    out = report_dir or Path("out") / "eval" / (workflow.stem + (f"_{fusion}" if fusion else ""))
    click.echo(f"report: {write_report(result, arrays, out)}")


COMMANDS = (scene, simulate, eval_cmd)
