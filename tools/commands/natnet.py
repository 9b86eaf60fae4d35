"""`uuomocap natnet probe|serve`: check a live OptiTrack (NatNet) stream, or imitate one.

probe  connects to Motive (or any NatNet server), listens a few seconds and reports the
       server, bitstream version, frame rate, points per frame, latency and every
       dropped/malformed packet: the first thing to run when plugging into a studio.
serve  replays a marker file (.c3d/.trc/.mcap) as a NatNet server on this machine, so the
       live graph (launch/live_natnet.yaml) can be run and tested without Motive.
"""

from __future__ import annotations

import signal
import sys
import time

import numpy as np

from uuomocap.commands import UserError, add_json_flag, emit


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "natnet",
        help="probe a live OptiTrack NatNet stream, or serve a marker file as one",
        description=__doc__,
    )
    sub = parser.add_subparsers(dest="natnet_cmd", metavar="CMD")
    parser.set_defaults(func=lambda args: (parser.print_help(sys.stderr), 2)[1])

    probe = sub.add_parser("probe", help="connect, listen, report rate / points / drops",
                           description="Connect to a NatNet server, receive frames for --seconds and report "
                                       "what arrived. Exit 0 when frames arrived, 1 when the server answered "
                                       "but sent no frames, 2 when no server answered.")
    _network_args(probe)
    probe.add_argument("--seconds", type=float, default=3.0, help="how long to listen (default 3)")
    add_json_flag(probe)
    probe.set_defaults(func=_probe)

    serve = sub.add_parser("serve", help="replay a marker file as a NatNet server (unicast or multicast)",
                           description="Stream a marker file's visible points as NatNet frames (unlabeled "
                                       "markers) to every client that connects, at the file's rate x --speed. "
                                       "Positions are sent in the file's axes; the file's up axis is printed.")
    serve.add_argument("file", help="marker file: .c3d, .trc or an .mcap recording")
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    serve.add_argument("--command-port", type=int, default=1510, help="NatNet command port (default 1510)")
    serve.add_argument("--bitstream", default="4.1", help="NatNet bitstream version to speak (3.0 .. 4.1+)")
    serve.add_argument("--multicast", action="store_true", help="send frames to --multicast-group instead")
    serve.add_argument("--multicast-group", default="239.255.42.99")
    serve.add_argument("--data-port", type=int, default=1511, help="multicast data port (default 1511)")
    serve.add_argument("--speed", type=float, default=1.0, help="x real time (default 1)")
    serve.add_argument("--loop", action="store_true", help="start over at the end (frame numbers keep rising)")
    serve.add_argument("--wait-client", type=float, default=0.0,
                       help="seconds to wait for a client before streaming (unicast; default: stream at once)")
    add_json_flag(serve)
    serve.set_defaults(func=_serve)


def _network_args(p) -> None:
    p.add_argument("--server", default="127.0.0.1", help="Motive's streaming address (default 127.0.0.1)")
    p.add_argument("--local", default="127.0.0.1", help="this machine's address on that network")
    p.add_argument("--multicast", action="store_true", help="Motive streams multicast (default unicast)")
    p.add_argument("--multicast-group", default="239.255.42.99")
    p.add_argument("--command-port", type=int, default=1510)
    p.add_argument("--data-port", type=int, default=1511)


def _probe(args) -> int:
    from tqdm import tqdm

    from uuomocap.protocol.natnet import NatNetClient

    try:
        client = NatNetClient(args.server, local_address=args.local, multicast=args.multicast,
                              multicast_group=args.multicast_group, command_port=args.command_port,
                              data_port=args.data_port)
        client.open()
    except OSError as exc:
        raise UserError(f"cannot open NatNet sockets on {args.local}: {exc}") from None
    with client:
        try:
            info = client.connect(timeout_s=min(5.0, max(1.0, args.seconds)))
        except TimeoutError as exc:
            raise UserError(f"{exc} (is streaming on in Motive, and --server its Local Interface?)") from None
        frames = []
        end = time.monotonic() + args.seconds
        with tqdm(total=round(args.seconds, 1), unit="s", file=sys.stderr, leave=False, disable=args.seconds <= 1,
                  bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s") as bar:
            while (left := end - time.monotonic()) > 0:
                frames += client.poll(min(0.1, left))
                elapsed = round(args.seconds - max(0.0, end - time.monotonic()), 1)
                if elapsed != bar.n:
                    bar.update(elapsed - bar.n)
        stamps = np.array([f.timestamp for f in frames])
        points = np.array([len(f.point_cloud()[0]) for f in frames]) if frames else np.zeros(0)
        latency = [x for f in frames if (x := client.latency_s(f)) is not None]
        labelled = sum(int(f.point_cloud()[2].sum()) for f in frames)
        data = {
            "server": f"{args.server}:{args.command_port}",
            "app": f"{info.app_name} {'.'.join(map(str, info.app_version))}",
            "natnet_version": ".".join(map(str, info.natnet_version)),
            "transport": f"multicast {info.multicast_group}:{info.data_port}" if info.multicast else "unicast",
            "frames": len(frames),
            "rate_hz": float(1.0 / np.median(np.diff(stamps))) if len(stamps) > 2 and np.median(np.diff(stamps)) > 0 else 0.0,
            "points_per_frame": {"mean": float(points.mean()) if len(points) else 0.0,
                                 "min": int(points.min()) if len(points) else 0,
                                 "max": int(points.max()) if len(points) else 0},
            "labelled_points": labelled,
            "rigid_bodies": len(frames[-1].rigid_bodies) if frames else 0,
            "skeletons": len(frames[-1].skeletons) if frames else 0,
            "latency_ms_median": float(np.median(latency) * 1e3) if latency else None,
            "stats": client.stats.as_dict(),
        }
    s = data["stats"]
    text = "\n".join([
        f"server:    {data['server']}  {data['app']}, NatNet {data['natnet_version']}, {data['transport']}",
        f"frames:    {data['frames']} in {args.seconds:g} s, {data['rate_hz']:.2f} Hz from the frame stamps",
        f"points:    {data['points_per_frame']['mean']:.1f} per frame (min {data['points_per_frame']['min']}, "
        f"max {data['points_per_frame']['max']}), {labelled} labelled in total",
        f"assets:    {data['rigid_bodies']} rigid bodies, {data['skeletons']} skeletons",
        "latency:   " + (f"{data['latency_ms_median']:.2f} ms mid-exposure -> transmit (median)"
                         if latency else "not reported"),
        f"problems:  {s['malformed']} malformed, {s['stale']} stale, {s['gaps']} frames missing, "
        f"{s['restarts']} restarts, {s['foreign']} foreign" + (f"; last error: {s['last_error']}" if s["last_error"] else ""),
    ])
    emit(args, data, text)
    return 0 if frames else 1


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _serve(args) -> int:
    from tqdm import tqdm

    from uuomocap.protocol import recording  # noqa: F401  (lets read_markers open .mcap)
    from uuomocap.protocol.markerio import MarkerFileError, read_markers
    from uuomocap.protocol.natnet import FrameOfData, NatNetError, NatNetServer, ServerInfo, labeled_marker_records

    try:
        major, minor = (int(x) for x in args.bitstream.split("."))
    except ValueError:
        raise UserError(f"--bitstream must look like 4.1, got {args.bitstream!r}") from None
    if not args.speed > 0:
        raise UserError("--speed must be > 0")
    try:
        md = read_markers(args.file, progress=True)
    except MarkerFileError as exc:
        raise UserError(str(exc)) from None
    info = ServerInfo(app_name="uuomocap natnet serve", app_version=(0, 1, 0, 0), natnet_version=(major, minor, 0, 0),
                      multicast=args.multicast, multicast_group=args.multicast_group, data_port=args.data_port)
    try:
        server = NatNetServer(info, host=args.host, command_port=args.command_port)
    except (OSError, NatNetError) as exc:
        raise UserError(f"cannot serve on {args.host}:{args.command_port}: {exc}") from None
    n_frames = len(md.positions)
    print(f"serving {md.source}: {n_frames} frames at {md.rate_hz:g} Hz x {args.speed:g}, up axis {md.up_axis}, "
          f"on {server.address[0]}:{server.address[1]} ({'multicast' if args.multicast else 'unicast'}); Ctrl-C stops",
          file=sys.stderr)
    sent = frame_number = 0
    # Stop cleanly on SIGTERM too (background jobs have SIGINT ignored).
    signal.signal(signal.SIGTERM, _interrupt)
    with server:
        deadline = time.monotonic() + args.wait_client
        while not args.multicast and not server.clients and time.monotonic() < deadline:
            server.serve_commands(0.1)
        start = time.monotonic()
        try:
            with tqdm(total=None if args.loop else n_frames, unit="frame", file=sys.stderr) as bar:
                while True:
                    i = frame_number % n_frames
                    if frame_number and i == 0 and not args.loop:
                        break
                    pts = md.positions[i][md.visible[i]]
                    frame = FrameOfData(frame_number=frame_number, labeled_markers=labeled_marker_records(
                        pts, ids=np.arange(1, len(pts) + 1)), timestamp=frame_number / md.rate_hz)
                    server.serve_commands(0.0)
                    sent += server.send_frame(frame) > 0
                    frame_number += 1
                    bar.update(1)
                    time.sleep(max(0.0, start + frame_number / (md.rate_hz * args.speed) - time.monotonic()))
        except KeyboardInterrupt:
            pass
    emit(args, {"frames": frame_number, "frames_delivered": sent, "clients_at_end": len(server.clients)},
         f"sent {frame_number} frames ({sent} reached a client)")
    return 0
