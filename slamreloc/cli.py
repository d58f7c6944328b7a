"""The `slamreloc` command line (typer + rich). Bad input: one line on stderr, exit status 2."""

from __future__ import annotations

import sys
from dataclasses import replace
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from slamreloc.errors import SlamrelocError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Camera relocalization with a lightweight scene-coordinate regressor.")


class Split(str, Enum):
    train = "train"
    test = "test"
    all = "all"


class FeatureName(str, Enum):
    sift = "sift"
    superpoint = "superpoint"


class Arch(str, Enum):
    paper = "paper"
    tiny = "tiny"
    wide = "wide"


class Method(str, Enum):
    regressor = "regressor"
    matching = "matching"


class Device(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


@app.command("map")
def map_cmd(
    dataset: Annotated[Path, typer.Argument(help="dataset folder (7-Scenes, TUM, synthetic)")],
    out: Annotated[Path, typer.Option("--out", help="map folder to write")],
    split: Annotated[str, typer.Option(help="train | test | all | sequence names")] = "train",
    features: Annotated[FeatureName, typer.Option(help="local features")] = FeatureName.sift,
    superpoint_weights: Annotated[Optional[Path], typer.Option(
        help="SuperPoint weights (.pth), needed with --features superpoint")] = None,
    arch: Annotated[Optional[Arch], typer.Option(
        help="regressor: wide (2.2 M, the default), paper (2.3 M), tiny (0.7 M)")] = None,
    epochs: Annotated[Optional[int], typer.Option(help="training epochs")] = None,
    device: Annotated[Device, typer.Option(help="training device")] = Device.auto,
) -> None:
    """Extract features, build scene-coordinate labels and train the regressor into OUT."""
    from slamreloc.datasets import load_dataset
    from slamreloc.mapping import MapConfig, build_map

    config = MapConfig(features=features.value, device=device.value)
    if arch is not None:
        config.arch = arch.value
    if features == FeatureName.superpoint:
        config.feature_options = {"weights": str(superpoint_weights or "")}
    if epochs is not None:
        config.train = replace(config.train, epochs=epochs)
    scene_map = build_map(load_dataset(dataset), out, split, config)
    _print_map(scene_map)


@app.command()
def evaluate(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder")],
    dataset: Annotated[Path, typer.Argument(help="dataset folder with ground-truth poses")],
    report: Annotated[Path, typer.Option("--report", help="REPORT.json to write")],
    split: Annotated[str, typer.Option(help="train | test | all | sequence names")] = "test",
    method: Annotated[Method, typer.Option(help="regressor, or the matching baseline")] =
    Method.regressor,
    poses: Annotated[Optional[Path], typer.Option(help="write estimated poses (TUM)")] = None,
    plot: Annotated[Optional[Path], typer.Option(help="write error curves and top view (PNG)")] =
    None,
    device: Annotated[Device, typer.Option(help="regressor device")] = Device.cpu,
) -> None:
    """Localize every frame of a split against MAP and score it against ground truth."""
    from slamreloc.pipeline import run_evaluation

    summary = run_evaluation(map_dir, dataset, report, split, method.value, poses, plot,
                             device.value)
    from slamreloc.evaluate import print_summary

    print_summary([summary])


@app.command()
def localize(
    map_dir: Annotated[Path, typer.Argument(metavar="MAP", help="map folder")],
    images: Annotated[list[Path], typer.Argument(help="image files")],
    intrinsics: Annotated[Optional[tuple[float, float, float, float]], typer.Option(
        help="FX FY CX CY in pixels (default: the map's camera, scaled to the image)")] = None,
    method: Annotated[Method, typer.Option()] = Method.regressor,
) -> None:
    """Print `name tx ty tz qx qy qz qw inliers` (camera-to-world) for each image."""
    from slamreloc.pipeline import localize_images

    errors = 0
    for line, status in localize_images(map_dir, images, intrinsics, method.value):
        if status == "error":
            errors += 1
            typer.echo(line, err=True)
        else:
            typer.echo(line)
    if errors:
        raise typer.Exit(2)


@app.command()
def demo(
    workdir: Annotated[Path, typer.Option(help="where the scene, map and reports go")] =
    Path("slamreloc-demo"),
    no_viewer: Annotated[bool, typer.Option("--no-viewer", help="do not serve the viewer")] =
    False,
    port: Annotated[int, typer.Option(help="viewer port")] = 8080,
) -> None:
    """The main job on the embedded synthetic scene: render, map, train, relocalize, report."""
    from slamreloc.demo import run_demo

    run_demo(workdir, viewer=not no_viewer, port=port)


def _print_map(scene_map) -> None:
    from slamreloc.progress import console

    lab, reg = scene_map.meta["labels"], scene_map.meta["regressor"]
    console.print(f"[green]map written[/green] to {scene_map.root}: {reg['arch']} regressor "
                  f"({reg['parameters'] / 1e6:.2f} M parameters, "
                  f"{scene_map.size_bytes() / 1e6:.1f} MB), trained on {lab['n_labelled']} "
                  "labelled keypoints")


def main() -> None:
    try:
        app()
    except (SlamrelocError, ValueError, OSError) as err:
        # one line, whatever the message holds (some libraries' messages span lines)
        print(f"error: {' '.join(str(err).split()) or type(err).__name__}", file=sys.stderr)
        sys.exit(2)
    except MemoryError:
        print("error: out of memory", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
