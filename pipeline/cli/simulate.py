"""``python -m pipeline simulate MODEL.h5 SCENARIO.yaml [...] [-o RESULT.h5] [--no-plots]``.

Steps the model of a file through scenarios (:func:`pipeline.apps.simulate.simulate`) and
prints the summary table (measured beside predicted), one line of integrator statistics
per run, and the files written.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["cmd_simulate", "add_simulate_parser"]


def cmd_simulate(args) -> int:
    from pipeline.apps.simulate import simulate  # here: the integrators load only for this command

    model = Path(args.model)
    output = Path(args.output) if args.output else Path("outputs") / f"{model.stem}_simulate.h5"
    res = simulate(model, [Path(p) for p in args.scenarios], output, plots=not args.no_plots)
    print(f"{model}: {len(res.scenarios)} scenario(s) in {res.wall_s:.1f} s")
    print(res.table())
    for s in res.scenarios:
        for run in s.runs:
            i = run.info
            dev = i.get("deviation_from_exact")  # absent for time-varying systems (spin_up)
            print(f"  {s.scenario.name:<14.14} {run.model:<36.36}"
                  + (f" m={run.mass:<6g}" if run.mass is not None else " " * 9)
                  + f" {i.get('method')} rtol={i.get('rtol'):g} atol={i.get('atol'):g}: "
                  f"{i.get('nfev')} RHS calls, {i.get('wall_s', 0):.2f} s"
                  + (f", max deviation from exact {max(dev.values()):.1e}" if dev else "")
                  + (f"; {i['coupling']}" if "coupling" in i else ""))
    for f in res.files:
        print(f"wrote {f}")
    return 0


def add_simulate_parser(subparsers):
    """Register ``simulate MODEL.h5 SCENARIO.yaml [...] [-o RESULT.h5]`` on an argparse
    subparsers object (``python -m pipeline simulate``)."""
    p = subparsers.add_parser(
        "simulate", help="step the reduced model of a file through test scenarios",
        description="Step the model of MODEL.h5 (read from the file only) through the "
                    "scenarios of SCENARIO.yaml (one scenario or a list; several files "
                    "allowed) and print measured vs predicted frequencies and deflections.")
    p.add_argument("model", help="HDF5 model file written by 'python -m pipeline run'")
    p.add_argument("scenarios", nargs="+", metavar="SCENARIO.yaml",
                   help="scenario file(s), e.g. configs/scenarios/*.yaml")
    p.add_argument("-o", "--output", help="RESULT.h5 (default outputs/<model>_simulate.h5); "
                   "CSV and PNG files go beside it as <stem>.<scenario>.csv/.png")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=cmd_simulate)
    return p
