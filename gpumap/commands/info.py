"""``gpumap info``: the backends this machine can run, and the one ``auto`` picks."""

from __future__ import annotations

from gpumap.commands.common import ArgumentParser, one_line

__all__ = ["main"]

DESCRIPTION = "list the backends this machine can run"


def main(argv: list[str] | None = None) -> int:
    ArgumentParser(prog="gpumap info", description=DESCRIPTION).parse_args(argv)
    import gpumap
    from gpumap.backends import make_backend

    spec = gpumap.SonarSpec.uniform(n_beams=4, n_bins=4)
    print(f"gpumap {gpumap.__version__}")
    works = []
    for name in gpumap.available_backends():
        try:
            b = make_backend(name, spec)
        except gpumap.BackendUnavailableError as e:  # a device is there, but it cannot run gpumap
            print(f"  {name:<11} cannot run: {one_line(e)}")
            continue
        works.append(b.name)
        print(f"  {b.name:<11} {b.device}")
    print(f"auto picks: {works[0]}")
    return 0
