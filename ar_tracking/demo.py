"""``ar-tracking demo``: the main job on the sample bag, ending in a report.

Runs the orientation graph (lockstep: imu_magnetometer, panorama_mapper,
hybrid_orientation_filter) on ``bags/rotation_sweep_authoring.mcap`` with the calibration
that came with it, evaluates the output against the bag's ground truth and writes the report
(HTML and PNG). Where the package is installed without the repository's bags/, the same
scenario is simulated first.
"""
from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

logger = logging.getLogger(__name__)

SAMPLE_BAG = 'rotation_sweep_authoring.mcap'


def sample_bag(workdir: Path) -> Path:
    """The committed sample bag, or a freshly simulated one of the same recipe."""
    checkout = Path(__file__).resolve().parents[1] / 'bags' / SAMPLE_BAG
    if checkout.is_file():
        return checkout
    from .sim.bagmaker import make_bag

    path = workdir / SAMPLE_BAG
    if not path.is_file():
        logger.info('no sample bag in the package; simulating %s', path)
        make_bag('rotation_sweep', path, seed=7, duration_s=20.0, session='authoring',
                 image_format='compressed', overwrite=True, profile='kind')
    return path


def run_demo(workdir: Path, quiet: bool = False) -> int:
    from .eval.console import strict_json
    from .eval.evaluate import evaluate_all
    from .eval.report import write_report
    from .ros.runner import GraphRunner

    workdir.mkdir(parents=True, exist_ok=True)
    bag = sample_bag(workdir)
    params = bag.with_name(bag.name[: -len(bag.suffix)] + '.params.yaml')
    print(f'1/3 running the graph on {bag}', file=sys.stderr)
    progress = None
    bar = None
    if not quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(desc='run', unit='msg', file=sys.stderr, leave=False)

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

    try:
        result = GraphRunner(
            bag, workdir / 'demo.out.mcap', params_files=[params] if params.is_file() else [],
            progress=progress, named_graph='orientation',  # exactly the nodes the README names
        ).run()
    finally:
        if bar is not None:
            bar.close()
    print(f'    {result.input_messages} input messages in {result.wall_s:.1f} s '
          f'({result.realtime_factor:.1f}x realtime), nodes: {", ".join(result.nodes)}', file=sys.stderr)
    print('2/3 evaluating against the ground truth', file=sys.stderr)
    metrics = strict_json(evaluate_all(result.out_path))
    (workdir / 'metrics.json').write_text(json.dumps(metrics, indent=2, sort_keys=True, allow_nan=False) + '\n')
    print('3/3 writing the report', file=sys.stderr)
    html = write_report(result.out_path, workdir / 'report.html', metrics)
    png = write_report(result.out_path, workdir / 'report.png', metrics)
    for topic, m in sorted(metrics.get('orientation', {}).items()):
        if 'error' not in m:
            print(f'{topic}: orientation rmse {m["rmse_deg"]:.2f} deg, heading rmse '
                  f'{m["heading_rmse_deg"]:.2f} deg, tilt rmse {m["tilt_rmse_deg"]:.2f} deg (n={m["n"]})')
    pano = metrics.get('panorama')
    if pano and 'tracking_rmse_deg' in pano:
        print(f'panorama/orientation: tracking rmse {pano["tracking_rmse_deg"]:.3f} deg relative to the first frame, '
              f'{pano.get("lost_frames", 0)} of {pano.get("frames", "?")} frames lost')
    print(f'report: {html}')
    print(f'figure: {png}')
    print(f'metrics: {workdir / "metrics.json"}')
    return 0
