"""The writing room: what makes data, run by the data stage
(`stages/data.py`) and the prepare CLI (`data/prepare.py`) only.

`convert.py`: the steps every converted dataset shares (shards, resumable
progress, skipped videos and their report, metadata, checksums, video
names); `generate.py`: the `Output` a generated dataset writes through;
`records.py`: the chunked record layout, whole folders and checksums;
`pool.py`: the worker processes. What a dataset holds and how one video is
made is its module's (`slotformer_jax/datasets/`); nothing outside this
room writes data (tests/test_layout.py).
"""
