"""Run a declared Monte-Carlo study from a small TOML or JSON file and write its report.

The file names a study kind (one of :data:`KINDS`: the declarations of the experiments that
define it, ``declare(grid, trials, seed, chunk, **options)``) and, optionally, its grid,
trials, seed, chunk and the kind's options, e.g. (JSON)::

    {"kind": "fir_covariance", "grid": {"input": ["white"], "N": [300], "sigma": [0.5]},
     "trials": 2000, "seed": 1, "chunk": 500}

or (TOML)::

    kind = "consistency"
    trials = 200
    options = {noise = "output"}
    [grid]
    N = [250, 1000, 4000]
    sigma = [0.5]

Keys left out take the kind's defaults (a grid, when given, names every factor of the
kind). The study's chunks go to ``DIR/study`` (Parquet, one file per finished chunk, and
``manifest.json``), its report (Markdown, CSV, figures) to
``DIR/report``. A run refuses a ``DIR/study`` that already holds results (chunk files) unless
``--resume`` is given; with ``--resume`` it computes only the missing chunks of the same
declaration, and a different declaration (grid, trials, seed, chunk, kind, options) is
refused by the study's manifest check instead of mixing results. The grid's factors are the
kind's (the ones its data generator reads); a trial's data do not depend on ``--trials``.

Run: ``python -m experiments.study DECLARATION [--trials N] [--workers K] [--resume]
[--out DIR] [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from experiments._common import experiment_parser, finish, note, output_dir

NAME = "study"
#: study kind -> module that declares it (``declare(grid, trials, seed, chunk, **options)``)
KINDS = {
    "fir_covariance": "experiments.sysid_fir_covariance",
    "fat_tails": "experiments.sysid_fat_tails",
    "consistency": "experiments.sysid_consistency",
    "greybox_consistency": "experiments.greybox_consistency",
}
KEYS = ("kind", "grid", "trials", "seed", "chunk", "options")
QUICK_TRIALS = 20


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__)
    parser.add_argument(
        "declaration",
        type=pathlib.Path,
        help="the study's declaration, a .toml or .json file (no default: required); "
        f"kinds: {', '.join(KINDS)}",
    )
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help=f"trials per grid point (default: the file's, else the kind's; {QUICK_TRIALS} "
        "with --quick)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes: 1 runs the chunks here; K > 1 starts a dask LocalCluster of K "
        "one-thread workers (pip install 'rkident[dask]')",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the study already in DIR/study (same declaration); without it a "
        "non-empty DIR/study is refused",
    )
    return parser


def read_declaration(path: pathlib.Path) -> dict:
    """The declaration in ``path`` (``.toml`` or ``.json``) as a dict with keys among
    :data:`KEYS`; ``kind`` one of :data:`KINDS`.

    Raises:
        ValueError: unreadable file, unknown suffix, unknown key or kind, a value of the wrong
            type (trials, seed and chunk are integers, grid and options tables); the message
            says which and what is allowed.
    """
    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        declaration = json.loads(path.read_text())
    elif suffix == ".toml":
        import tomllib

        declaration = tomllib.loads(path.read_text())
    else:
        raise ValueError(f"{path}: a declaration is a .toml or .json file, not {path.suffix!r}.")
    if not isinstance(declaration, dict):
        raise ValueError(f"{path}: the declaration must be a table/object of {KEYS}.")
    unknown = sorted(set(declaration) - set(KEYS))
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown}; a declaration has {KEYS}.")
    if declaration.get("kind") not in KINDS:
        raise ValueError(
            f"{path}: kind {declaration.get('kind')!r} is not a known study kind; "
            f"choose one of {sorted(KINDS)}."
        )
    for key in ("trials", "seed", "chunk"):
        value = declaration.get(key, 0)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{path}: {key} must be an integer, got {value!r}.")
    for key in ("grid", "options"):
        if not isinstance(declaration.get(key, {}), dict):
            raise ValueError(
                f"{path}: {key} must be a table (TOML) / object (JSON), got {declaration[key]!r}."
            )
    return declaration


def declare(declaration: dict, trials: int | None = None):
    """The :class:`sysid.studies.Study` of ``declaration`` (see :func:`read_declaration`),
    built by its kind's module; ``trials`` overrides the declaration's.

    Raises:
        ValueError: an option the kind does not take; the kind's and the study's checks of
            the values (:class:`~sysid.errors.InputValidationError`).
    """
    import importlib
    import inspect

    module = importlib.import_module(KINDS[declaration["kind"]])
    allowed = set(inspect.signature(module.declare).parameters) - set(KEYS)
    unknown = sorted(set(declaration.get("options", {})) - allowed)
    if unknown:
        raise ValueError(
            f"the kind {declaration['kind']!r} has no option(s) {unknown}; its options are "
            f"{sorted(allowed)}."
        )
    keywords = {
        key: declaration[key] for key in ("grid", "trials", "seed", "chunk") if key in declaration
    }
    if trials is not None:
        keywords["trials"] = trials
    return module.declare(**keywords, **declaration.get("options", {}))


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}.")
    try:
        declaration = read_declaration(args.declaration)
    except (OSError, ValueError) as err:
        parser.error(str(err))
    out = output_dir(args, NAME)
    folder = out / "study"
    if any(folder.glob("chunks/*.parquet")) and not args.resume:
        parser.error(
            f"{folder} already holds results of a study; pass --resume to continue it (same "
            "declaration), or choose another --out."
        )
    trials = QUICK_TRIALS if args.quick and args.trials is None else args.trials
    try:  # the kind's and the study's checks of the values (InputValidationError)
        study = declare(declaration, trials)
    except ValueError as err:
        parser.error(f"{args.declaration}: {err}")
    note(
        f"study {declaration['kind']}: {len(study.points)} grid points x {study.trials} trials, "
        f"{study.n_chunks} chunk(s) each, {args.workers} worker(s)"
    )
    from sysid.errors import InputValidationError

    try:
        if args.workers > 1:
            from dask.distributed import Client

            from sysid.studies import local_cluster

            with local_cluster(args.workers) as cluster, Client(cluster) as client:
                study.run(folder, client=client)
        else:
            study.run(folder)
    except InputValidationError as err:  # another declaration's results (--resume), or a
        parser.error(f"{args.declaration}: {err}")  # grid value its data generator refuses
    report = study.report(out / "report")
    finish(out, report.read_text())
    return study


if __name__ == "__main__":  # every heavy import is inside main: --help answers at once
    main()
