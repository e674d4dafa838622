"""``hil view LOG.mcap``: the log as a Rerun recording (.rrd beside it, or --save), optionally opened in the viewer."""
from __future__ import annotations

import shutil
import subprocess
import sys

from ..errors import ConfigError


def register(sub) -> None:
    p = sub.add_parser("view", help="make a Rerun recording (.rrd, with a blueprint) of an MCAP log and open it")
    p.add_argument("log", help="MCAP log of 'hil run'")
    p.add_argument("--save", metavar="OUT.rrd", default=None, help="where to write the recording "
                   "(default: beside the log, LOG.rrd)")
    p.add_argument("--spawn", action="store_true", help="open the recording in the Rerun viewer")
    p.set_defaults(func=cmd_view)


def cmd_view(args) -> int:
    from ..view import write_rrd

    out, data = write_rrd(args.log, args.save)
    if not data.log.complete:
        print(f"hil view: warning: {args.log}: {data.log.problem()}; the recording shows what was read "
              f"({data.log.message_count} messages)", file=sys.stderr)
    print(f"recording: {out}")
    if args.spawn:
        exe = shutil.which("rerun") or str((__import__("pathlib").Path(sys.executable).with_name("rerun")))
        try:
            subprocess.Popen([exe, "--bind", "127.0.0.1", str(out)], start_new_session=True)
        except OSError as e:
            raise ConfigError(f"cannot start the Rerun viewer ({exe}): {e.strerror}") from None
    return 0
