"""Run bookkeeping: where a run's artifacts live (`paths`), what each was
made from (`identity`), the settings a workdir was run with (`settings`),
and one writer at a time (`lock`).

Nothing here reads data, builds a model or trains: these are plain files
and plain dicts, so every floor above (data generation, training,
evaluation, the tasks, the official-weights converter) can use them.
"""
