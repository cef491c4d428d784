"""Data parallelism over every device of every host.

One mesh axis, 'data': the global batch is split along it, parameters and
optimiser state are replicated. `jax.jit` with these shardings inserts the
gradient all-reduce itself. The same code serves 1 CPU, N fake CPU devices
(`XLA_FLAGS=--xla_force_host_platform_device_count=N`), a GPU node and a
multi-host pod (after `jax.distributed.initialize()`).
"""

from __future__ import annotations

import collections
from collections.abc import Iterator
from typing import Any

import jax
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec
import numpy as np

DATA_AXIS = 'data'


def make_mesh() -> Mesh:
  """A 1-D mesh over all devices of all processes."""
  return Mesh(np.asarray(jax.devices()), (DATA_AXIS,))


def one_device_per_process() -> Mesh:
  """A 'data' mesh of the first device of each process (for models too
  small to gain from more: the readout heads)."""
  first = {}
  for device in jax.devices():
    first.setdefault(device.process_index, device)
  return Mesh(np.asarray([first[p] for p in sorted(first)]), (DATA_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
  """Leading (batch) axis split over devices, the rest replicated."""
  return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
  return NamedSharding(mesh, PartitionSpec())


def per_host_batch_size(global_batch_size: int, mesh: Mesh) -> int:
  """The share of one host; the global batch must split evenly over devices."""
  num_devices = mesh.devices.size
  if global_batch_size % num_devices:
    raise ValueError(
        f'batch size {global_batch_size} is not divisible by the '
        f'{num_devices} devices; choose a multiple of {num_devices}')
  return global_batch_size // jax.process_count()


def check_host_rows(mesh: Mesh) -> None:
  """Checks that this process's devices hold rows ``[p * B, (p + 1) * B)``
  of a batch-sharded global array (B: the per-host batch), the rows
  `data.pipeline.train_batches` gives host ``p``.

  Raises:
    ValueError: the mesh orders the devices of the processes otherwise.
  """
  num_rows = mesh.shape[DATA_AXIS]  # one row per 'data' device
  indices = batch_sharding(mesh).addressable_devices_indices_map((num_rows,))
  rows = sorted({index[0].indices(num_rows)[0]
                 for index in indices.values()})
  first = jax.process_index() * len(rows)
  if rows != list(range(first, first + len(rows))):
    raise ValueError(
        f'process {jax.process_index()} holds rows {rows} of the global '
        f'batch (one row per device), not the block {first}..'
        f'{first + len(rows) - 1} its training batches are drawn for; the '
        'mesh must list the devices of process 0 first, then 1, ...')


def to_global_batch(local_batch: dict[str, np.ndarray], mesh: Mesh,
                    sharding: NamedSharding | None = None
                    ) -> dict[str, jax.Array]:
  """Assembles each host's slice into global arrays sharded on 'data', or
  as `sharding` says (e.g. [K, B, ...]: B on 'data')."""
  if sharding is None:
    sharding = batch_sharding(mesh)
  return jax.tree.map(
      lambda x: jax.make_array_from_process_local_data(sharding, x),
      local_batch)


def prefetch_to_device(host_batches: Iterator[dict[str, np.ndarray]],
                       mesh: Mesh, size: int = 2,
                       sharding: NamedSharding | None = None
                       ) -> Iterator[tuple[dict[str, np.ndarray],
                                           dict[str, jax.Array]]]:
  """Yields ``(host batch, global batch)`` with up to `size` batches already
  handed to the devices (`to_global_batch`), so that the transfer of the next
  batch overlaps the step that runs (a device put is asynchronous on
  accelerators; nothing here waits for the devices).

  The next host batch is taken when the current one is handed out, i.e.
  while the previous step still runs. An error of `host_batches` is raised
  after the batches before it are handed out, at the step it would have
  been raised without prefetching. Closing this closes `host_batches`.
  `sharding`: where the batches go (see `to_global_batch`).
  """
  if size < 1:
    raise ValueError(f'size must be >= 1, got {size}')
  ready: collections.deque = collections.deque()
  failure: BaseException | None = None
  ended = False
  try:
    while True:
      while failure is None and not ended and len(ready) < size:
        try:
          host = next(host_batches)
        except StopIteration:
          ended = True
          break
        except Exception as error:  # pylint: disable=broad-except
          failure = error
          break
        ready.append((host, to_global_batch(host, mesh, sharding)))
      if not ready:
        if failure is not None:
          raise failure
        return
      yield ready.popleft()
  finally:
    ready.clear()
    close = getattr(host_batches, 'close', None)
    if close is not None:
      close()


def replicate(tree: Any, mesh: Mesh) -> Any:
  return jax.device_put(tree, replicated_sharding(mesh))


def to_host(tree: Any) -> Any:
  """Fetches (fully addressable or replicated) arrays as numpy."""
  return jax.tree.map(np.asarray, jax.device_get(tree))


def gather_to_host(tree: Any) -> Any:
  """Global batch-sharded arrays -> numpy on every host."""
  if jax.process_count() == 1:
    return jax.tree.map(np.asarray, tree)
  # Imported here: multihost_utils is only needed with several processes.
  from jax.experimental import multihost_utils  # pylint: disable=g-import-not-at-top
  return multihost_utils.process_allgather(tree, tiled=True)
