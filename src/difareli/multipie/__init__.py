"""Multi-PIE, the paper's benchmark, from a user's own copy (the database is licensed: nothing here ships it).

- :mod:`~difareli.multipie.layout`: the frontal-camera tree and its file names;
- :mod:`~difareli.multipie.protocols`: the authors' JSON pair lists, or both protocols drawn from a seed;
- :mod:`~difareli.multipie.build`: preprocessing into an encodings store with a ``protocols.json``
  (``difareli-multipie root=<copy> out_dir=<store>``), which ``difareli-benchmark`` runs on unchanged;
- :mod:`~difareli.evaluation.published`: the paper's Table I figures, for ``difareli-table published=...``.

docs/evaluation.md describes the protocols, the metric rule and the commands.
"""
