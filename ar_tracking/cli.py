"""``ar-tracking``: make bags, run the graph on a bag, evaluate, benchmark, demo.

Every error the user can cause (a missing or damaged bag, a bad params file, an unknown
scenario) ends in one line on stderr and a non-zero exit code, never a traceback.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

EXIT_USAGE = 2
EXIT_FAILED = 1

logger = logging.getLogger('ar_tracking')


def _progress_bar(enabled: bool, desc: str) -> tuple[Callable[[int, int], None] | None, Callable[[], None]]:
    """A tqdm progress callback (done, total) and a closer; disabled when not wanted."""
    if not enabled:
        return None, lambda: None
    from tqdm import tqdm

    bar: dict[str, Any] = {}

    def update(done: int, total: int) -> None:
        if 'b' not in bar:
            bar['b'] = tqdm(total=total, desc=desc, unit='msg', file=sys.stderr, leave=False, mininterval=0.5)
        b = bar['b']
        b.update(done - b.n)

    def close() -> None:
        if 'b' in bar:
            bar['b'].close()

    return update, close


# --- commands ------------------------------------------------------------------------------

def cmd_make_bag(args: argparse.Namespace) -> int:
    from .sim.bagmaker import make_bag

    update, close = _progress_bar(not args.quiet and sys.stderr.isatty(), 'make-bag')
    progress = (lambda f: update(int(f * 1000), 1000)) if update else None
    try:
        path = make_bag(
            args.scenario, args.out, seed=args.seed, duration_s=args.duration, session=args.session,
            storage=args.storage, image_format=args.image_format, overwrite=True, progress=progress,
            profile=args.profile,
            imu_time_offset_s=None if args.imu_time_offset_ms is None else args.imu_time_offset_ms * 1e-3,
            readout_s=None if args.readout_ms is None else args.readout_ms * 1e-3,
            camera_latency_s=None if args.camera_latency_ms is None else args.camera_latency_ms * 1e-3,
            world_photos=args.world_photos, parallax=args.parallax,
        )
    finally:
        close()
    print(path)
    return 0


def cmd_annotate(args: argparse.Namespace) -> int:
    """Store annotations from an authoring bag: patches of its panorama at the given positions,
    with the bag's GPS fix and the panorama's estimated orientation (Langlotz sec. 3.2, 5)."""
    from .annotate import PositionError, annotate_bag, parse_position, read_positions

    rows: list = []
    bad: list[str] = []
    try:
        if args.positions:
            got, bad = read_positions(args.positions, args.form)
            rows += got
        for form in ('pixel', 'azel', 'bearing'):
            for item in getattr(args, form) or []:
                text, sep, numbers = item.rpartition('=')
                try:
                    if not sep:
                        raise PositionError(f'expected TEXT=A,B, got {item!r}')
                    rows.append(parse_position(text, numbers, form))
                except PositionError as exc:
                    bad.append(f'--{form} {item!r}: {exc}; skipped')
    except PositionError as exc:
        print(f'ar-tracking annotate: error: {exc}', file=sys.stderr)
        return EXIT_FAILED
    for line in bad:
        print(line, file=sys.stderr)
    positions: Any = rows
    if args.simulated_user:
        from .eval.annotation_metrics import simulated_user_positions

        user = simulated_user_positions(args.bag)
        positions = lambda first_ns: rows + user(first_ns)  # noqa: E731
    elif not rows and not args.png:
        print('ar-tracking annotate: error: no positions (--positions FILE, --pixel/--azel/--bearing '
              'TEXT=A,B); run once with --png pano.png to pick them on the panorama', file=sys.stderr)
        return EXIT_FAILED
    update, close = _progress_bar(not args.quiet and sys.stderr.isatty(), 'annotate')
    progress = (lambda f: update(int(f * 1000), 1000)) if update else None
    try:
        report = annotate_bag(args.bag, args.store, positions=positions, patch_px=args.patch_px,
                              author=args.author, panorama_id=args.panorama_id, edr=not args.no_edr,
                              replace=args.replace, params_files=args.params_file, png=args.png,
                              landmarks=args.landmarks, support_landmarks=args.support_landmarks,
                              progress=progress)
    finally:
        close()
    for text, reason in report.skipped:
        print(f'skipped {text!r}: {reason}', file=sys.stderr)
    if report.duplicates:
        print(f'{report.duplicates} annotation(s) already stored for panorama {report.panorama_id} '
              '(same position); not added again (--replace authors the panorama again)', file=sys.stderr)
    print(json.dumps({'panorama_id': report.panorama_id, 'stored': len(report.stored),
                      'skipped': len(report.skipped), 'duplicates': report.duplicates,
                      'replaced': report.replaced, 'landmarks': report.landmarks,
                      'orientation_source': report.orientation_source,
                      'heading_sigma_deg': _finite_or_none(report.heading_sigma_deg),
                      'ahrs_disagreement_deg': _finite_or_none(report.ahrs_disagreement_deg),
                      'latitude_deg': report.latitude_deg, 'longitude_deg': report.longitude_deg,
                      'png': report.png or None}))
    return 0 if (report.stored or report.duplicates or (not rows and not args.simulated_user)) else 1


def _finite_or_none(x: float) -> float | None:
    return round(x, 4) if math.isfinite(x) else None


LATENCY_LABEL = 'orientation/global (input stamp published -> received)'


def cmd_run(args: argparse.Namespace) -> int:
    from .ros.runner import GraphRunner, check_rate

    check_rate(args.rate, lockstep=True)
    bag = Path(args.bag)
    out = Path(args.out) if args.out else Path('out') / (bag.name.split('.')[0] + '.out.mcap')
    params = list(args.params_file or [])
    sidecar = _sidecar_params(bag)
    if sidecar is not None and not args.no_sidecar:
        logger.info('using calibration %s (disable with --no-sidecar)', sidecar)
        params.insert(0, sidecar)
    bridge = None
    if args.foxglove is not None:  # the live view: every output served over Foxglove's WebSocket
        from .ros.foxglove import FoxgloveBridge

        bridge = FoxgloveBridge(port=args.foxglove)
        print(f'Foxglove live view: open {bridge.url} in Foxglove (layout: config/foxglove_layout.json)',
              file=sys.stderr)
    update, close = _progress_bar(not args.quiet and sys.stderr.isatty(), 'run')
    try:
        result = GraphRunner(
            bag, out, params_files=params, nodes=args.nodes, rate=args.rate, storage=args.storage,
            copy_images=args.copy_images, executor=args.executor, progress=update, named_graph=args.graph,
            output_taps=[bridge.tap] if bridge is not None else None, compression=args.compression,
        ).run()
    finally:
        close()
        if bridge is not None:
            bridge.close()
    summary = {
        'out': str(result.out_path), 'nodes': result.nodes, 'not_started': result.not_started,
        'input_messages': result.input_messages,
        'output_messages': result.output_messages, 'wall_s': round(result.wall_s, 3),
        'start_s': round(result.start_s, 3), 'executor': result.executor,
        'bag_duration_s': round(result.bag_duration_s, 3), 'realtime_factor': round(result.realtime_factor, 2),
        'interrupted': result.interrupted,
        'lost_deliveries': result.lost_deliveries,
        'superseded_deliveries': result.superseded_deliveries,
        'dropped_deliveries': result.dropped_deliveries,
        # node -> topic -> count (see RunResult)
        'superseded': result.superseded, 'dropped': result.dropped, 'lost': result.lost,
        # node -> why its thread died (realtime); any entry makes the exit code 1
        'failed_nodes': result.failed_nodes,
    }
    if args.rate > 0:
        # realtime: inputs published to each node vs processed, orientation/global latency
        summary['live'] = result.live_summary()
    elif result.live_cpu_s:  # lockstep over node processes: where the time went
        summary['cpu_s'] = {node: round(cpu, 3) for node, cpu in sorted(result.live_cpu_s.items())}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f'{result.out_path}: {result.output_messages} messages from {", ".join(result.nodes)} '
              f'({result.input_messages} inputs, {result.wall_s:.1f} s, {result.realtime_factor:.1f}x realtime; '
              f'{result.start_s:.1f} s to start, executor {result.executor})'
              + (' - interrupted' if result.interrupted else ''))
        for kind, table in (('superseded (latest value only)', result.superseded),
                            ('dropped (queue overflow)', result.dropped), ('lost (not delivered)', result.lost)):
            for node, topics in sorted(table.items()):
                print(f'  {node}: ' + ', '.join(f'{n} {kind} on {t}' for t, n in sorted(topics.items())))
        if args.rate > 0:
            live = summary['live']
            for node, topics in live['inputs'].items():
                print(f'  {node}: {live["dropped"][node]} inputs dropped ('
                      + ', '.join(f'{c["processed"]} of {c["published"]} on {t}' for t, c in topics.items()) + ')')
            if live['latency_n']:
                print(f'  {LATENCY_LABEL}: latency p50 {live["latency_ms_p50"]:.1f} ms, '
                      f'p95 {live["latency_ms_p95"]:.1f} ms ({live["latency_n"]} messages)')
    for node, why in sorted(result.failed_nodes.items()):
        print(f'ar-tracking run: error: node {node} died: {why}', file=sys.stderr)
    if result.failed_nodes:
        return EXIT_FAILED
    return 130 if result.interrupted else 0


def _sidecar_params(bag: Path) -> Path | None:
    """The calibration file make-bag writes next to a bag: <bag stem>.params.yaml."""
    stem = bag.name[: -len(bag.suffix)] if bag.suffix else bag.name
    candidate = bag.with_name(stem + '.params.yaml')
    return candidate if candidate.is_file() else None


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .eval.console import format_console, strict_json
    from .eval.evaluate import evaluate_all
    from .eval.report import write_report

    metrics = strict_json(evaluate_all(args.bag, align=args.align_world))
    if args.align_world != 'none':
        print(f'world frames aligned to the truth by one constant {args.align_world} per estimate '
              '(the truth is not north-referenced): absolute heading is not scored', file=sys.stderr)
    recovered = _recovered_line(Path(args.bag))
    if recovered:
        print(recovered, file=sys.stderr if args.json else sys.stdout)
    if args.json:
        # strict JSON: null for what could not be computed, never NaN or Infinity
        print(json.dumps(metrics, indent=None if args.compact else 2, sort_keys=True, allow_nan=False))
        if not args.report:
            return 0
    report = Path(args.report) if args.report else Path(args.bag).with_suffix('.report.html')
    written = write_report(args.bag, report, metrics)
    if not args.json:
        print(format_console(metrics, args.bag))
        print(f'report: {written}')
    return 0


def _recovered_line(bag: Path) -> str | None:
    """One line when the bag is an unfinished MCAP that was recovered (its writer was killed):
    the metrics then cover only what reached the file."""
    from .io.bags import is_unfinished_mcap, scan_unfinished_mcap

    if not is_unfinished_mcap(bag):
        return None
    rec = scan_unfinished_mcap(bag)  # cached: the evaluation already scanned it
    return (f'{bag}: recovered from an unfinished MCAP (the writer was killed): scored its '
            f'{rec.message_count} complete messages, {(rec.end_ns - rec.start_ns) * 1e-9:.1f} s of bag time')


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(args.workdir), quiet=args.quiet)


def cmd_bench(args: argparse.Namespace) -> int:
    from .eval.bench import run_bench

    try:
        results = run_bench(Path(args.workdir), duration_s=args.duration, areas=args.areas)
    except ValueError as exc:
        print(f'ar-tracking bench: error: {exc}', file=sys.stderr)
        return EXIT_USAGE
    text = json.dumps(results, indent=2, sort_keys=True)
    if args.out:
        Path(args.out).write_text(text + '\n')
    print(text)
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """Play a bag on its topics (the bag_replay node with command-line options)."""
    from .ros.runner import check_rate

    args.rate = check_rate(args.rate, lockstep=False)
    from .nodes.bag_replay import main as replay_main

    ros_args = ['--ros-args', '-p', f'bag_path:={args.bag}', '-p', f'rate:={float(args.rate)}',
                '-p', f'start_offset_s:={float(args.start_offset)}', '-p', f'loop:={str(args.loop).lower()}']
    if args.topics:
        ros_args += ['-p', 'topics:=[' + ','.join(args.topics) + ']']
    if args.remap:
        ros_args += ['-p', 'remap:=[' + ','.join(f'"{r}"' for r in args.remap) + ']']
    return replay_main(['bag_replay'] + ros_args)


def cmd_convert_euroc(args: argparse.Namespace) -> int:
    """An EuRoC MAV folder (mav0/cam0, imu0, ground truth) as a bag the graph can run on."""
    from .io.euroc import euroc_to_bag

    if args.groundtruth is None:
        hint = _euroc_groundtruth_hint(Path(args.folder))
        if hint:
            print(hint, file=sys.stderr)
    print(euroc_to_bag(args.folder, args.out, args.groundtruth, args.invert_gt_quaternion,
                       gt_frame=args.gt_frame, storage=args.storage, overwrite=args.overwrite))
    return 0


def _euroc_groundtruth_hint(folder: Path) -> str | None:
    """One line when an EuRoC folder has no mav0/state_groundtruth_estimate0/data.csv (the
    ground truth used by default) but a ground-truth file elsewhere, saying how to use it."""
    mav0 = folder if folder.name == 'mav0' else folder / 'mav0'
    if (mav0 / 'state_groundtruth_estimate0' / 'data.csv').is_file():
        return None
    root = folder.parent if folder.name == 'mav0' else folder
    candidates = sorted(
        p for pattern in ('*/*', '*', 'mav0/*/*') for p in root.glob(pattern)
        if p.is_file() and p.suffix.lower() in ('.txt', '.csv')
        and ('groundtruth' in p.name.lower() or 'ground_truth' in p.name.lower() or '_gt' in p.name.lower()
             or 'groundtruth' in p.parent.name.lower())
    )
    if not candidates:
        return None
    gt = candidates[0]
    orb = gt.name.upper().endswith('_GT.TXT')  # ORB-SLAM's files store R_cam_world, camera poses
    return (f'convert-euroc: no mav0/state_groundtruth_estimate0/data.csv, so no ground truth is used; '
            f'{gt} looks like one: add --groundtruth {gt}'
            + (' --invert-gt-quaternion (ORB-SLAM *_GT.txt files store R_cam_world)' if orb
               else ' (and --invert-gt-quaternion if it stores R_cam_world, --gt-frame body for IMU poses)'))


# --- parser --------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='ar-tracking',
        description='AR tracking on ROS 2: make bags, run the node graph on them, evaluate, benchmark.',
    )
    parser.add_argument('-v', '--verbose', action='store_true', help='log debug messages')
    # -q on every command: only errors and the result
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument('--quiet', '-q', action='store_true',
                        help='print only errors and the result (no progress bar, no info or warning logs, '
                             "the nodes' logs included)")
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    _add = sub.add_parser

    def add_parser(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        kwargs.setdefault('description', kwargs.get('help'))
        return _add(name, parents=[common], **kwargs)

    sub.add_parser = add_parser  # type: ignore[method-assign]

    p = sub.add_parser('make-bag', help='simulate a scenario into a bag with ground truth')
    p.add_argument('scenario',
                   help='one of: rotation_sweep (a phone swept around in place: camera, IMU, magnetometer '
                        'with disturbances, GPS), robot_arcs (a robot moving a camera in front of fiducial '
                        'markers, with IMU), handheld_desk (a hand-held rolling-shutter camera over a desk, '
                        'for SLAM)')
    p.add_argument('--seed', type=int, default=0,
                   help='random seed of the simulation: the same seed gives the same bag, byte for byte (default 0)')
    p.add_argument('--duration', type=float, default=60.0, help='seconds (default 60)')
    p.add_argument('--session', default='authoring', choices=['authoring', 'browsing'],
                   help='rotation_sweep: authoring = the first visit of the spot (annotations are made on it), '
                        'browsing = a later visit from a few metres away, other lighting (default authoring)')
    p.add_argument('--out', '-o', required=True, help='output bag (.mcap file, or a directory with --storage sqlite3)')
    p.add_argument('--storage', default='mcap', choices=['mcap', 'sqlite3'],
                   help='rosbag2 storage: mcap (one file, default) or sqlite3 (a directory with metadata.yaml)')
    p.add_argument('--image-format', default='raw', choices=['raw', 'compressed'],
                   help='camera images as sensor_msgs/Image (raw, default) or CompressedImage JPEG (compressed)')
    p.add_argument('--profile', default='hard', choices=['hard', 'kind'],
                   help="sensor realism: 'hard' (default) = rotation_sweep: a realistic phone (hand acceleration, "
                        'field turns that keep |B| and dip, residual iron after a rough calibration, gyro bias drift, '
                        'camera-IMU time offset); robot_arcs: a real camera (lens distortion in camera_info, display '
                        'gamma, defocus, 155 deg/s pans with motion blur, an occluder, IMU bias walks, the IMU mount '
                        "with a lever arm only on /tf_static); 'kind' = the earlier, easier simulators")
    p.add_argument('--imu-time-offset-ms', type=float, default=None, metavar='MS',
                   help='rotation_sweep: the IMU and magnetometer stamps are this much later than the camera\'s for '
                        'the same instant (default: the profile\'s, 2-8 ms either sign in hard, 0 in kind)')
    p.add_argument('--readout-ms', type=float, default=None, metavar='MS',
                   help='rotation_sweep: the camera\'s rolling shutter reads its rows out over this time after the '
                        'frame\'s stamp, written to the sidecar (0: a global shutter; default: the profile\'s, 8-30 ms '
                        'in hard, left out of the sidecar for panorama_mapper to estimate, 0 in kind)')
    p.add_argument('--camera-latency-ms', type=float, default=None, metavar='MS',
                   help='rotation_sweep: each camera frame is logged (arrives) this long after its stamp, behind '
                        'the IMU samples of its time (default: the profile\'s, 30-120 ms in hard, 0 in kind)'),
    p.add_argument('--world-photos', default=None, metavar='DIR',
                   help='rotation_sweep: cut the camera frames from a panorama of these photos of a full turn '
                        '(pano.txt gives their focal lengths, e.g. ../shared/data/pano_grail) instead of the '
                        'rendered street: real textures, same motion, sensors and truth, no annotations')
    p.add_argument('--parallax', action=argparse.BooleanOptionalAction, default=None,
                   help='rotation_sweep: render each frame from where the camera is (in front of the body\'s turning '
                        'axis, with the hand\'s sway), so that near objects move against far ones; --no-parallax: from '
                        'the spot (default: the profile\'s, on in hard, off in kind; a photo world has none)')
    p.set_defaults(func=cmd_make_bag)

    p = sub.add_parser('annotate', help='store annotations from an authoring bag (patches of its panorama at given positions)')
    p.add_argument('bag', help='authoring-session bag')
    p.add_argument('--store', '-s', required=True, help='annotation store: an SQLite file (created if missing), sqlite:///path, or '
                        'postgresql://user@host/db[?schema=NAME] (PostGIS, shared by many users)')
    p.add_argument('--positions', help='file of "text,a,b" rows (a line "# form: pixel|azel|bearing" sets the '
                                       'form of the rows after it; default --form); bad rows are skipped, one line each')
    p.add_argument('--form', default='pixel', choices=['pixel', 'azel', 'bearing'],
                   help='form of the --positions rows: map pixel u,v (default); azimuth,elevation in the panorama '
                        'frame (deg); compass bearing,elevation in the world (deg, via the estimated orientation)')
    p.add_argument('--pixel', action='append', metavar='TEXT=U,V', help='an annotation at map pixel (u, v) (repeatable)')
    p.add_argument('--azel', action='append', metavar='TEXT=AZ,EL',
                   help='an annotation at azimuth/elevation in the panorama frame, deg (repeatable)')
    p.add_argument('--bearing', action='append', metavar='TEXT=B,E',
                   help='an annotation at compass bearing (from true north, clockwise) / elevation, deg (repeatable)')
    p.add_argument('--png', help='also write the authoring panorama with a degree grid here (to pick positions on)')
    p.add_argument('--simulated-user', action='store_true',
                   help='evaluation only (simulated bags): add an annotation where each /ground_truth/annotations '
                        'anchor appears in the panorama, as a user clicking on it would (read by ar_tracking.eval; '
                        'the stored orientation is still estimated)')
    p.add_argument('--replace', action='store_true',
                   help="delete this panorama's annotations and landmarks first (default: anchors already stored "
                        'at the same position are skipped, so annotating a bag twice does not duplicate)')
    p.add_argument('--params-file', action='append',
                   help='device calibration (params file of imu_magnetometer / hybrid_orientation_filter; '
                        'default <bag>.params.yaml next to the bag)')
    p.add_argument('--patch-px', type=int, default=16, choices=[8, 16, 24, 32],
                   help='side of the stored image patch of each annotation, map pixels (default 16)')
    p.add_argument('--author', default='', help='author name stored with each annotation')
    p.add_argument('--panorama-id', default=None,
                   help='id of this authoring panorama in the store (default: derived from the bag)')
    p.add_argument('--no-edr', action='store_true', help='8-bit map instead of the EDR map')
    p.add_argument('--landmarks', type=int, default=24, metavar='N',
                   help='also store up to N landmarks of the panorama (distinctive patches that help '
                        'align it when browsing; never shown); 0: none (default 24)')
    p.add_argument('--support-landmarks', type=int, default=4, metavar='K',
                   help='with landmarks, also up to K landmarks next to each annotation (they pin '
                        'its parallax when browsing from another spot); 0: none (default 4)')
    p.set_defaults(func=cmd_annotate)

    p = sub.add_parser('run', help='run the graph a bag suits (or --graph/--nodes); record the outputs')
    p.add_argument('bag', help='input bag (rosbag2 mcap or sqlite3, or ROS 1 .bag)')
    p.add_argument('--out', '-o', help='output bag (default out/<bag>.out.mcap)')
    p.add_argument('--rate', type=float, default=0.0,
                   help='0 (default): lockstep, reproducible; R > 0 (finite): realtime at R x bag speed with /clock')
    p.add_argument('--params-file', action='append', help='ROS 2 params file (repeatable; later wins)')
    p.add_argument('--no-sidecar', action='store_true', help='ignore <bag>.params.yaml next to the bag')
    which = p.add_mutually_exclusive_group()
    which.add_argument('--nodes', nargs='+', metavar='NODE',
                       help='only these nodes: imu_magnetometer, panorama_mapper, hybrid_orientation_filter, '
                            'annotation_matcher, ar_view, keyframe_slam_mapper, marker_tracker, '
                            'visual_inertial_filter')
    which.add_argument('--graph', default='auto', choices=['auto', 'orientation', 'annotations', 'slam', 'markers', 'all'],
                       help='which graph to start (default auto: every node the bag has inputs for, but '
                            'keyframe_slam_mapper not on a bag with /imu/mag - a phone turned in place, '
                            'where SLAM cannot initialise); orientation = imu_magnetometer, panorama_mapper, '
                            'hybrid_orientation_filter; annotations = orientation + annotation_matcher, ar_view; '
                            'slam = keyframe_slam_mapper; markers = marker_tracker, visual_inertial_filter')
    p.add_argument('--storage', choices=['mcap', 'sqlite3'],
                   help='storage of the output bag (default: mcap, or from the --out name)')
    p.add_argument('--compression', default='lz4', choices=['lz4', 'zstd', 'none'],
                   help='chunk compression of an MCAP output (default lz4: a quarter of the time of zstd on '
                        'the overlay images, files ~1.6x larger; rosbags, mcap and Foxglove read all three)')
    p.add_argument('--copy-images', action='store_true', help='also copy the camera images into the output')
    p.add_argument('--executor', default='auto', choices=['auto', 'threads', 'processes', 'single', 'events', 'multi'],
                   help='how the nodes run (default auto: processes with --rate, and in lockstep for 2+ nodes on a '
                        'bag of 30 s or more; events otherwise). processes: each node in its own process, as ros2 '
                        'launch starts them, so a slow node cannot stall the others (in lockstep the runner carries '
                        'the messages in a fixed order: the same output, nodes working in parallel); threads: each '
                        'node on its own thread and executor in this process (realtime); single/events/multi put '
                        'every node on one executor of this process (multi: MultiThreadedExecutor, realtime only)')
    p.add_argument('--json', action='store_true', help='print the run summary as JSON')
    p.add_argument('--foxglove', type=int, nargs='?', const=8765, default=None, metavar='PORT',
                   help='serve the outputs live over the Foxglove WebSocket protocol on 127.0.0.1:PORT '
                        '(default 8765): orientation as a 3D frame, panorama, AR overlay, SLAM points and path; '
                        'layout in config/foxglove_layout.json')
    p.set_defaults(func=cmd_run)

    p = sub.add_parser('evaluate', help='metrics of an output bag against its ground truth')
    p.add_argument('bag', help='output bag of ar-tracking run (with the ground truth it copied)')
    p.add_argument('--json', action='store_true', help='print the metrics as one JSON object')
    p.add_argument('--compact', action='store_true', help='JSON on one line')
    p.add_argument('--report', help='write the report here (.html or .png); default <bag>.report.html')
    p.add_argument('--align-world', choices=['none', 'heading', 'rotation'], default='none',
                   help='for truth whose world frame is not north-referenced (motion capture): turn each '
                        'estimate onto the truth by one constant heading offset or rotation before scoring '
                        '(default none: absolute orientation is scored)')
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser('demo', help='the whole job on the sample bag, ending in a report')
    p.add_argument('--workdir', default='out/demo', help='where the output bag and the report go (default out/demo)')
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser('bench', help='speed of the graph and the cores on this machine, as JSON')
    p.add_argument('--workdir', default='out/bench', help='where benchmark bags are made and kept (default out/bench)')
    p.add_argument('--duration', type=float, default=60.0, help='length of the benchmark bag, s')
    p.add_argument('--areas', nargs='+', metavar='AREA',
                   help='only these areas: graph, orientation, orientation_seeds, orientation_photo_worlds (the '
                        'same with the frames cut from the real photo turns in ../shared/data), panorama, markers_vi, '
                        'annotations, slam, store (annotation store: radius query on 100,000 records, SQLite '
                        'and PostGIS; 8 writers + 8 readers), foxglove (wall time the live view adds) (default: all)')
    p.add_argument('--json', action='store_true', help='(the output is always JSON)')
    p.add_argument('--out', '-o', help='also write the JSON here')
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser('replay', help='publish a bag on its topics (like ros2 bag play)')
    p.add_argument('bag', help='bag to publish (rosbag2 mcap or sqlite3, or ROS 1 .bag)')
    p.add_argument('--rate', type=float, default=1.0,
                   help='playback speed: 1 = as recorded, 2 = twice as fast; finite and > 0 (default 1)')
    p.add_argument('--start-offset', type=float, default=0.0, help='seconds of the bag to skip (default 0)')
    p.add_argument('--loop', action='store_true', help='start again at the end (the clock jumps back; nodes reset)')
    p.add_argument('--topics', nargs='+', help='only these bag topics')
    p.add_argument('--remap', nargs='+', help='from:=to remappings of bag topics')
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser('convert-euroc', help='convert an EuRoC MAV folder (mav0/...) into a bag')
    p.add_argument('folder', help='the dataset folder (holding mav0/) or mav0 itself')
    p.add_argument('--out', '-o', required=True, help='output bag (.mcap added for mcap storage)')
    p.add_argument('--groundtruth', metavar='CSV',
                   help='ground-truth CSV: timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z (default: '
                        'mav0/state_groundtruth_estimate0/data.csv when present)')
    p.add_argument('--invert-gt-quaternion', action='store_true',
                   help='the CSV stores R_cam_world (e.g. the ORB-SLAM V101_GT.txt files)')
    p.add_argument('--gt-frame', choices=['camera', 'body'],
                   help='what the ground-truth rows are poses of: camera (cam0, default for --groundtruth) or '
                        "body (the IMU; moved to the camera with cam0's T_BS; default for "
                        'state_groundtruth_estimate0)')
    p.add_argument('--storage', default='mcap', choices=['mcap', 'sqlite3'],
                   help='rosbag2 storage: mcap (one file, default) or sqlite3 (a directory)')
    p.add_argument('--overwrite', action='store_true', help='replace an existing output bag')
    p.set_defaults(func=cmd_convert_euroc)
    return parser


def _user_errors() -> tuple[type[BaseException], ...]:
    """Exception families that are the user's input, reported as one line: every error of the
    package (:class:`ar_tracking.errors.ArTrackingError`: bad bags, parameters, stores, scenario
    arguments, ...) and files that are missing or not readable."""
    from .errors import ArTrackingError

    return (ArTrackingError, FileNotFoundError, PermissionError)


#: Commands that start rclpy nodes in this process (their logs go through rcutils, not logging).
_ROS_COMMANDS = ('run', 'demo', 'replay', 'bench')


def _quiet_everything(command: str) -> Callable[[], None]:
    """-q: Python warnings off, and the nodes' rcutils loggers at ERROR (the default level of
    every logger, set before the nodes exist, so that their info/warn lines are not printed).
    Returns what undoes it (main() called in-process, e.g. by a test, leaves no trace)."""
    import warnings

    filters = list(warnings.filters)
    undo: list[Callable[[], None]] = [lambda: warnings.filters.__setitem__(slice(None), filters)]
    warnings.simplefilter('ignore')
    if command in _ROS_COMMANDS:
        try:
            import rclpy.logging

            previous = rclpy.logging.get_logger_effective_level('')
            rclpy.logging.set_logger_level('', rclpy.logging.LoggingSeverity.ERROR)
            undo.append(lambda: rclpy.logging.set_logger_level('', previous))
        except Exception as exc:  # no rclpy: nothing to quiet
            logger.debug('node logs not quieted: %s', exc)

    def restore() -> None:
        for step in reversed(undo):
            step()

    return restore


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    quiet = bool(getattr(args, 'quiet', False)) and not args.verbose
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.ERROR if quiet else logging.INFO,
        format='%(levelname)s %(name)s: %(message)s',
        stream=sys.stderr,
    )
    restore = _quiet_everything(args.command) if quiet else None
    try:
        return int(args.func(args) or 0)
    except _user_errors() as exc:
        print(f'ar-tracking {args.command}: error: {exc}', file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f'ar-tracking {args.command}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (| head): no traceback for that
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    finally:
        if restore is not None:
            restore()


if __name__ == '__main__':
    raise SystemExit(main())
