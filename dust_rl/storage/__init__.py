"""What a run writes and reads back: atomic files, digest-checked checkpoint folders, cache records, run folders.

Nothing here loads a pickle: every file is JSON, a memory map, or a ``weights_only`` torch file whose digest
is checked before it is read.
"""
