"""PHYRE: rollouts rendered by tools/render_phyre.py -> convert -> read back.

``phyre`` cannot be installed here, so the render script runs against a
small stand-in module with the same functions (folds, the 100k-action cache,
a simulator returning colour-index images, the palette); what the script
writes is the documented layout the converter reads.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import dataset_fixtures as fx
from slotformer_jax import datasets
from slotformer_jax.datasets import phyre
from slotformer_jax.data import prepare
from slotformer_jax.data import sources
from dataset_fixtures import data_section

SCENE = 16          # stand-in scene size (PHYRE: 256)
MAX_FRAMES = 7      # render_phyre.py --max_frames (paper: 15)
KEEP = 6            # --num_frames of the conversion (paper: 15)
REPO = Path(__file__).resolve().parents[2]

# A stand-in for the parts of the phyre package the script uses. Action
# x < 0.5 gives a 3-frame simulation, otherwise 9 frames (cut to
# MAX_FRAMES by the script); the ball (colour 2) falls one row per frame and
# rests from frame 5 on; y > 0.9 is an invalid action (no images); the
# simulated outcome is x > 0.25, which differs from the cache for task 1.
FAKE_PHYRE = textwrap.dedent('''
    import numpy as np
    SCENE_HEIGHT = SCENE_WIDTH = {scene}
    PALETTE = np.array([[255, 255, 255], [243, 79, 70], [107, 206, 187],
                        [24, 119, 242], [75, 74, 164], [185, 202, 210],
                        [0, 0, 0], [252, 223, 227]], np.uint8)
    TASKS = ['00000:000', '00000:001', '00001:000', '00030:000']

    def get_fold(eval_setup, fold):
      assert eval_setup == 'ball_within_template', eval_setup
      return (TASKS[:1], (TASKS[1], TASKS[3]), (TASKS[2],))

    class _Cache:
      def get_sample(self, tasks, num_actions):
        actions = np.array([[0.1, 0.5, 0.2], [0.7, 0.2, 0.3],
                            [0.8, 0.95, 0.1], [0.3, 0.4, 0.5],
                            [0.6, 0.6, 0.6]], np.float32)
        statuses = np.array([[1, 1, 1, -1, -1], [-1, -1, 0, 1, -1],
                             [1, -1, 1, -1, 1]])[:len(tasks)]
        return {{'actions': actions, 'simulation_statuses': statuses}}

    def get_default_100k_cache(tier):
      assert tier == 'ball'
      return _Cache()

    class _Simulation:
      def __init__(self, images, status):
        self.images, self.status = images, status

    class _Simulator:
      def __init__(self, tasks):
        self.tasks = list(tasks)

      def simulate_action(self, task_index, action, stride, need_images,
                          need_featurized_objects):
        assert stride == 60 and need_images
        x, y, r = (float(v) for v in action)
        if y > 0.9:
          return _Simulation(None, 0)
        length = 3 if x < 0.5 else 9
        images = np.zeros((length, SCENE_HEIGHT, SCENE_WIDTH), np.int64)
        images[:, -1, :] = 6                     # black ground line
        for t in range(length):
          row = min(t, 5)
          images[t, row, 2 + task_index] = 2     # the green ball
        return _Simulation(images, 1 if x > 0.25 else -1)

    def initialize_simulator(tasks, tier):
      return _Simulator(tasks)

    def observations_to_uint8_rgb(scene):
      return PALETTE[scene][::-1]
''').format(scene=SCENE)


def load_render_script():
  spec = importlib.util.spec_from_file_location(
      'render_phyre', REPO / 'tools' / 'render_phyre.py')
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module


@pytest.fixture(scope='module')
def rendered(tmp_path_factory):
  base = tmp_path_factory.mktemp('phyre')
  (base / 'fake_phyre.py').write_text(FAKE_PHYRE)
  sys.path.insert(0, str(base))
  try:
    script = load_render_script()
    out = base / 'rollouts'
    assert script.main([f'--out={out}', '--fold=0', '--num_workers=1',
                        f'--max_frames={MAX_FRAMES}', '--data_ratio=0.008',
                        '--pos_ratio=0.5', '--phyre_module=fake_phyre']) == 0
  finally:
    sys.path.remove(str(base))
    sys.modules.pop('fake_phyre', None)
  return base, out


def read_index(split_dir: Path) -> list[dict]:
  return [json.loads(line) for line in
          (split_dir / phyre.INDEX_FILE).read_text().splitlines()]


def convert_args(source: Path, data_dir: Path, *extra: str) -> list[str]:
  return ['--dataset=phyre', f'--source={source}', f'--data_dir={data_dir}',
          f'--resolution={SCENE}', f'--num_frames={KEEP}', '--num_workers=1',
          '--no_progress', *extra]


def source_for(data_dir: Path, split: str) -> sources.VideoSource:
  return datasets.get_video_source(data_section(
      name='phyre', data_dir=str(data_dir), resolution=(SCENE, SCENE)), split)


def test_render_script_writes_the_documented_layout(rendered):
  _, out = rendered
  meta = json.loads((out / phyre.META_FILE).read_text())
  assert meta['format'] == phyre.FORMAT
  assert (meta['tier'], meta['eval_setup'], meta['fps'], meta['background'],
          meta['frame_size']) == ('ball', 'ball_within_template', 1, 'black',
                                  [SCENE, SCENE])
  # Per task int(int(2000 * 0.5) * 0.008) = 8 solving and 8 failing actions
  # at most (train; val: int(int(500 * 0.5) * 0.008) = 2 each). Template
  # 00030 is not among the BALL tier's 25 templates and is left out.
  train = read_index(out / 'train')
  assert {r['task'] for r in train} == {'00000:000', '00000:001'}
  # Task 0: 3 solving + 2 failing cached actions, task 1: 1 + 3 (its
  # status-0 action is never drawn); the invalid action (y > 0.9) of task 0
  # is simulated without images and left out, keeping the other ids.
  ids = [int(r['id']) for r in train]
  assert len(ids) == 8 and ids == sorted(set(ids)) and max(ids) <= 8
  assert all(r['action'][1] <= 0.9 for r in train)
  for record in train:
    strip = np.asarray(fx.Image.open(out / 'train' / 'frames' /
                                     f'{record["id"]}.png'))
    assert strip.shape == (record['num_frames'] * SCENE, SCENE, 3)
    assert record['num_frames'] == (3 if record['action'][0] < 0.5
                                    else MAX_FRAMES)
    # The simulated outcome is stored, not the cache's.
    assert record['success'] == (record['action'][0] > 0.25)
    # Black background; the ground line (PHYRE's black) became white, and
    # the image is flipped so that it is at the top here.
    frames = strip.reshape(-1, SCENE, SCENE, 3)
    assert (frames[:, -1, 0] == 0).all()
    assert (frames[:, 0, :] == 255).all()
  val = read_index(out / 'val')
  assert {r['task'] for r in val} == {'00001:000'}
  assert 3 <= len(val) <= 4   # 2 + 2 drawn, minus the invalid one if drawn
  # Re-running resumes: nothing is rendered again.
  script = load_render_script()
  assert script._done_ids(str(out / 'train' / phyre.INDEX_FILE)) == {
      r['id'] for r in train}


def test_official_action_selection(rendered):
  """RandomState(fold) reproduces the official np.random.seed(fold) draws."""
  script = load_render_script()
  rng = np.random.default_rng(3)
  statuses = rng.choice([-1, 0, 1], size=(4, 50))
  actions = rng.random((50, 3))
  chosen = script.select_actions(statuses, actions, num_pos=3, num_neg=5,
                                 seed=7)
  np.random.seed(7)
  expected = []
  for task, status in enumerate(statuses):
    pos, neg = actions[status == 1].copy(), actions[status == -1].copy()
    np.random.shuffle(pos)
    np.random.shuffle(neg)
    expected += [(task, a, 1) for a in pos[:3]] + [(task, a, 0)
                                                   for a in neg[:5]]
  assert len(chosen) == len(expected)
  for (t1, a1, l1), (t2, a2, l2) in zip(chosen, expected):
    assert (t1, l1) == (t2, l2)
    np.testing.assert_array_equal(a1, a2)


def test_convert_pad_cut_and_labels(rendered, tmp_path):
  _, out = rendered
  assert prepare.main(convert_args(out, tmp_path / 'data', '--splits=train')
                      ) == 0
  train = source_for(tmp_path / 'data', 'train')
  index = {r['id']: r for r in read_index(out / 'train')}
  assert len(train) == len(index)
  for i in range(len(train)):
    item = train[i]
    record = index[str(item['rollout_id'].item(), 'utf-8')]
    video = item['video']
    assert video.shape == (KEEP, SCENE, SCENE, 3) and video.dtype == np.uint8
    real = min(record['num_frames'], KEEP)
    assert int(item['num_frames']) == real
    strip = np.asarray(fx.Image.open(out / 'train' / 'frames' /
                                     f'{record["id"]}.png'))
    frames = strip.reshape(-1, SCENE, SCENE, 3)
    np.testing.assert_array_equal(video[:real], frames[:real])
    # Short rollouts are padded with their last frame.
    np.testing.assert_array_equal(video[real:],
                                  np.repeat(frames[real - 1:real],
                                            KEEP - real, 0))
    # The ball rests from frame 5 on: frames 0..5 move (6), when rendered.
    assert int(item['num_moving_frames']) == (3 if real == 3 else 6)
    assert int(item['label']) == int(record['success'])
    np.testing.assert_allclose(item['action'], record['action'], rtol=1e-6)
    assert str(item['task'].item(), 'utf-8') == record['task']
    assert int(item['template']) == int(record['task'][:5])


def test_num_moving_frames():
  frames = np.zeros((6, 2, 2, 3), np.uint8)
  frames[:, 0, 0, 0] = [0, 1, 2, 3, 3, 3]
  assert phyre.num_moving_frames(frames) == 4
  frames[:, 0, 0, 0] = np.arange(6)
  assert phyre.num_moving_frames(frames) == 6


def _layout(base: Path, records: list[tuple[dict, np.ndarray]]) -> Path:
  """A hand-written source: meta.json + train index + frame strips."""
  root = base / 'PHYRE'
  fx.write_json(root / phyre.META_FILE, {
      'format': phyre.FORMAT, 'format_version': phyre.FORMAT_VERSION,
      'tier': 'ball', 'eval_setup': 'ball_within_template', 'fold': 0,
      'fps': 1, 'max_frames': MAX_FRAMES, 'background': 'black',
      'frame_size': [SCENE, SCENE], 'splits': ['train']})
  lines = []
  for record, strip in records:
    if strip is not None:
      fx.write_png(root / 'train' / 'frames' / f'{record["id"]}.png', strip)
    lines.append(json.dumps(record) if isinstance(record, dict) else record)
  (root / 'train' / 'frames').mkdir(parents=True, exist_ok=True)
  (root / 'train' / phyre.INDEX_FILE).write_text('\n'.join(lines) + '\n')
  return root


def _record(rollout_id: str, num_frames: int) -> dict:
  return {'id': rollout_id, 'task': '00002:013', 'action': [0.1, 0.2, 0.3],
          'success': True, 'num_frames': num_frames}


def _strip(num_frames: int, width: int = SCENE) -> np.ndarray:
  return fx.noise_video(1, num_frames * SCENE, width)[0]


def test_bad_inputs_are_skipped_and_reported(tmp_path):
  root = _layout(tmp_path, [
      (_record('000000', 4), _strip(4)),                    # fine
      (_record('000001', 4), _strip(4)),                    # fine
      (_record('000002', 4), _strip(4, width=SCENE + 1)),   # wrong width
      (_record('000003', 5), _strip(4)),                    # count mismatch
      (_record('000004', 4), None),                         # no PNG
      ({'id': '000005', 'task': '00002:013'}, None),        # broken line
  ])
  result = prepare.run(prepare.build_parser().parse_args(convert_args(
      root, tmp_path / 'data', '--splits=train',
      '--max_skip_fraction=0.7')))
  assert result.num_examples == {'train': 2}
  assert result.skip_counts() == {'train': {
      'frame_size_mismatch': 1, 'frame_count_mismatch': 1,
      'unreadable_frame': 1, 'bad_annotation': 1}}


def test_missing_parts_name_the_layout(tmp_path, capsys):
  root = _layout(tmp_path, [(_record('000000', 2), _strip(2))])
  assert prepare.main(convert_args(root, tmp_path / 'data')) == 1
  err = capsys.readouterr().err
  assert 'val/rollouts.jsonl not found' in err
  assert 'tools/render_phyre.py' in err
  (root / phyre.META_FILE).unlink()
  with pytest.raises(FileNotFoundError, match='meta.json not found'):
    phyre.discover(root, 'train', phyre.Options())
  fx.write_json(root / phyre.META_FILE, {'format': 'something else'})
  with pytest.raises(ValueError, match='format'):
    phyre.discover(root, 'train', phyre.Options())
