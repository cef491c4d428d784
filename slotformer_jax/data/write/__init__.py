"""Offline writing: dataset converters, the array_record writer, media
decoding and the synthetic generator. Run-time reading lives in `data/`."""
