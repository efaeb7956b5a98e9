"""The ``pgs`` command line: one module per command group (:mod:`.runs`, :mod:`.files`,
:mod:`.experiments`; :mod:`.common` what they share), joined here into one parser with one
error policy (a bad input: one line and exit status 2, never a traceback)."""
from __future__ import annotations

import argparse
import sys

from baseline.cli import experiments, files, runs
from baseline.cli.common import _config_sets, _lpips_weights, _one_line, _print_results, _version

# main, and the helpers the Python API and the tests call
__all__ = ["main", "_config_sets", "_lpips_weights", "_print_results"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="pgs", description="anchor-based 3DGS compression toolkit: "
                                 "HAC, HAC++ and Predict-GS side by side")
    ap.add_argument("--version", action="version", version=f"pgs {_version()}")
    sub = ap.add_subparsers(dest="cmd", required=True)
    for group in (runs, files, experiments):
        group.add_parsers(sub)

    args = ap.parse_args(argv)
    from baseline import memory, registry
    from baseline.device import keep_freed_memory

    keep_freed_memory()          # trainings, decodes and renders reuse their freed blocks
    try:
        registry.ensure_loaded()
        return args.fn(args)
    except KeyboardInterrupt as e:     # TrainingStopped says where its checkpoint is
        print(f"pgs {args.cmd}: interrupted" + (f": {e}; run it again with --resume to continue"
                                               if str(e) else ""), file=sys.stderr)
        return 130
    except KeyError as e:          # a missing key: its name, not its repr
        print(f"pgs {args.cmd}: error: missing {e.args[0] if e.args else e}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, OSError) as e:
        print(f"pgs {args.cmd}: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as e:
        if not memory.is_allocation_failure(e):
            return _internal_error(args, e)
        # an allocation no step named (AllocationError names its own)
        msg = str(e) if isinstance(e, memory.AllocationError) else memory.describe(
            f"in pgs {args.cmd}", e)
        print(f"pgs {args.cmd}: error: {_one_line(msg)}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - never a traceback to a user; say it is a bug
        return _internal_error(args, e)

def _internal_error(args, e: BaseException) -> int:
    print(f"pgs {args.cmd}: internal error ({type(e).__name__}: {_one_line(e)}); please "
          f"report it with the command that caused it", file=sys.stderr)
    return 2
