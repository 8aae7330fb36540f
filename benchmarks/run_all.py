"""`make bench`: runs every ``benchmarks/bench_*.py`` module's ``main()`` in turn.

Each benchmark prints its figures and writes ``bench-results/<name>.json``. Pass names to
run a subset: ``python -m benchmarks.run_all workspace studio``.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
import time

import benchmarks


def main(argv: list[str] | None = None) -> int:
    wanted = set(argv if argv is not None else sys.argv[1:])
    names = sorted(m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_"))
    failed = []
    for name in names:
        short = name.removeprefix("bench_")
        if wanted and short not in wanted:
            continue
        print(f"\n=== bench {short} ===", flush=True)
        start = time.perf_counter()
        try:
            importlib.import_module(f"benchmarks.{name}").main()
        except Exception as err:  # one broken benchmark must not hide the others' figures
            failed.append(short)
            print(f"bench {short} FAILED: {type(err).__name__}: {err}", flush=True)
        print(f"=== {short}: {time.perf_counter() - start:.1f} s ===", flush=True)
    if failed:
        print(f"\nfailed benchmarks: {', '.join(failed)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
