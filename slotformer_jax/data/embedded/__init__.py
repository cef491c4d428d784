"""The embedded (generated) datasets as their readers see them.

One file per family: its generation parameters (which, with the generator's
version, name the folder the dataset lives in), the folder, and what a
complete dataset holds. Reading needs these to find a dataset; the
generators (`data/convert/`) import them from here to write it, so a folder
name has one definition. Nothing here generates or writes.
"""
