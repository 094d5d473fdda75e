"""``hel-warp train``: tune and fit the surrogate collision model on a collision data set (sec. 4.2).

One XGBoost model per target, Optuna (TPE + pruning) over n_estimators, max_depth,
learning_rate, colsample_bytree and reg_alpha; writes MODEL_DIR with the XGBoost JSON
models, metadata.json, metrics.json, the flattened forest.json and report/ figures.
Rerunning the same command resumes the Optuna studies (sqlite:///MODEL_DIR/study.db).
"""

from __future__ import annotations

from hel_warp.cli.commands._common import add_json_flag, emit, finite_float


def add_parser(subparsers):
    p = subparsers.add_parser("train", help="train the surrogate collision model (XGBoost + Optuna)",
                              description=__doc__)
    p.add_argument("--data", required=True, help="data set directory written by `hel-warp dataset --out`")
    p.add_argument("--out", required=True, help="model directory to write (MODEL_DIR)")
    p.add_argument("--form", choices=("contact", "contact_spin", "paper"), default="contact",
                   help="contact: contact-frame features and impulses, momentum exact (default); "
                        "contact_spin: the same for spinning spheres (a data set made with --spin-fraction; the "
                        "engine's particle_spin); paper: the paper's 6 velocities -> u, v, w of particle 1, central "
                        "impacts only")
    p.add_argument("--trials", type=int, default=50, help="finished Optuna trials per target, in all (default 50)")
    p.add_argument("--storage", default=None,
                   help="Optuna storage URL shared by workers (default sqlite:///MODEL_DIR/study.db)")
    p.add_argument("--samples-limit", type=int, default=None, help="use only the first N data-set rows")
    p.add_argument("--timeout", type=finite_float, default=None, help="search budget in seconds (all targets)")
    p.add_argument("--seed", type=int, default=0, help="seed of the split, sampler and XGBoost (default 0)")
    p.add_argument("--nthread", type=int, default=1, help="XGBoost threads per trial (default 1)")
    p.add_argument("--jobs", type=int, default=2, help="trials run side by side (default 2; the order in which they finish steers the sampler, so "
                        "only --jobs 1 gives the same model for a seed every time)")
    p.add_argument("--search-space", default=None, metavar="JSON",
                   help='overrides of the tuned ranges, e.g. \'{"n_estimators": [800, 3000], "max_depth": [8, 12]}\'')
    p.add_argument("--no-target-scale", action="store_true",
                   help="contact form: fit impulse_n and impulse_t as they are, not per cos_angle / sin_angle "
                        "(the default: fewer, shallower trees for the same error)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-report", action="store_true", help="skip the report figures")
    add_json_flag(p)
    return p


def run(args) -> int:
    import sys

    from hel_warp.cli.commands._common import require
    from surrogate.features import load_collision_data
    from surrogate.train import TrainConfig, train

    require(args.samples_limit is None or args.samples_limit > 0, "--samples-limit must be > 0")
    space = None
    if args.search_space is not None:
        import json

        from hel_warp.errors import ConfigError

        try:
            space = {k: tuple(v) for k, v in json.loads(args.search_space).items()}
        except (ValueError, TypeError, AttributeError):
            raise ConfigError(f"--search-space must be a JSON object of [low, high] ranges (got {args.search_space!r})"
                              ) from None
    config = TrainConfig(form=args.form, trials=args.trials, storage=args.storage, timeout=args.timeout,
                         seed=args.seed, nthread=args.nthread, jobs=args.jobs, search_space=space,
                         progress=not args.no_progress and sys.stderr.isatty(), report=not args.no_report,
                         target_scale=not args.no_target_scale)
    data = load_collision_data(args.data, samples_limit=args.samples_limit)
    log = (lambda msg: print(msg, file=sys.stderr)) if args.json else print
    metadata = train(data, args.out, config, log=log)
    if args.json:
        emit(metadata["metrics"], True)
    return 0
