"""`fieldtool view PROJECT`: the picking viewer on its own (the TUI starts the same server)."""

from __future__ import annotations

import argparse
import sys
import threading


def cmd_view(args: argparse.Namespace) -> int:
    from fieldtool.viewer import images, picks, registry, server  # lazy: viser and the viewer, not for every command

    if args.mode and args.mode not in picks.MODES:
        print(f"fieldtool: error: --mode {args.mode!r}: one of {', '.join(picks.MODES)}", file=sys.stderr)
        return 2
    if args.image and args.image not in images.KINDS:
        print(f"fieldtool: error: --image {args.image!r}: one of {', '.join(images.KINDS)}", file=sys.stderr)
        return 2

    def on_pick(field: str, value) -> None:
        print(f"saved {field} = {value}", flush=True)

    running = registry.running_viewer(args.project)  # one viewer per project: attach to the running one
    if running is not None:
        print(f"a picking viewer already runs for this project (pid {running.pid}); use it:", flush=True)
        print(f"picking viewer at {running.url}", flush=True)
        print(f"  over SSH, on your computer run:  {running.ssh_hint}", flush=True)
        print(f"  then open {running.local_url}", flush=True)
        return 0
    handle = server.start_viewer(args.project, host=args.host, port=args.port, on_pick=on_pick)
    if handle.warning:
        print(handle.warning, file=sys.stderr, flush=True)
    for note in handle.notes:
        print(note, flush=True)
    if args.image:
        handle.show_image(args.image)
    handle.set_mode(args.mode or handle.next_mode())
    print(f"picking viewer at {handle.url}  (Ctrl-C to stop)", flush=True)
    if handle.host in ("127.0.0.1", "localhost", "::1"):
        print(f"  over SSH, on your computer run:  {handle.ssh_hint}", flush=True)
        print(f"  then open {handle.local_url}", flush=True)
    print("  the URL holds a key made for this launch: only a page opened from it can use the viewer", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        pass
    finally:
        handle.stop()
    return 0


def register(sub) -> None:
    """Add `fieldtool view` to the CLI's subparsers."""
    p = sub.add_parser("view", help="open the picking viewer (web page) for a project file")
    p.add_argument("project", help="project file (TOML); picks are saved into it")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; anything else exposes the page to the network)",
    )
    p.add_argument(
        "--port",
        type=int,
        default=None,
        help="TCP port (default: the project's viewer.port, chosen free at the first launch and "
        "remembered; 0: a free port this time)",
    )
    p.add_argument(
        "--mode", help="pick mode to start in: gcp, section, roi, masks, stable, edges, edges1, edges2, divergence"
    )
    p.add_argument("--image", help="image to show: frame, working, ortho, image1, image2, dem_plot")
    p.set_defaults(func=cmd_view)
