"""``hil bus``: CAN captures read back as CANopen (docs/formats.md).

hil bus decode run.blf                  # every frame: NMT, SYNC, EMCY, heartbeat, SDO, PDO fields
hil bus decode run.log --eds my.eds     # field names and data types from the drive's EDS
"""

from __future__ import annotations

import collections
from pathlib import Path
from typing import Annotated

import typer

bus_app = typer.Typer(name="bus", help="CAN captures (.blf .asc .log .csv) read back as CANopen.", no_args_is_help=True)


@bus_app.command()
def decode(
    path: Annotated[Path, typer.Argument(help="a capture: .blf, .asc, .log (candump -L) or .csv")],
    eds: Annotated[Path | None, typer.Option("--eds", help="the drive's EDS (default: the shipped one)")] = None,
    limit: Annotated[int | None, typer.Option("--limit", min=1, help="print at most this many frames")] = None,
) -> None:
    """Print each frame as CANopen, then a count per kind."""
    from drivers.capture import read_capture
    from drivers.decode import Decoder, summary

    decoder = Decoder(eds)
    kinds: collections.Counter[str] = collections.Counter()
    t0_s: float | None = None
    lines: list[str] = []
    for msg in read_capture(path):  # read whole before printing: a bad file prints one line, nothing else
        frame = decoder.decode(msg)
        t0_s = frame.t_s if t0_s is None else t0_s
        kinds[frame.kind] += 1
        if limit is None or len(lines) < limit:
            lines.append(frame.line(t0_s))
    print("\n".join(lines))
    print(f"{sum(kinds.values())} frames: {summary(kinds)}")


def register(app: typer.Typer) -> None:
    app.add_typer(bus_app)
