"""Streaming services of fingerprint (docs/design.md §2, §7).

Pure (no zenoh): ``topics`` (key expressions), ``messages`` and ``wire`` (message models, wire format),
``registry`` (fingerprint dictionary entries and its query protocol), ``models`` (fingerprint
construction), ``pipeline`` (frame → γ-maps, detections, tracks), ``convert`` (results → messages),
``recording`` (MCAP files), ``sources`` (frame sources), ``units``, ``runtime``, ``schemas_gen``.
On the bus: ``bus`` (zenoh sessions), ``nodes`` (publisher, processor, recorder), ``viewing`` (Rerun,
figures). Front end: ``cli`` (the `fp` command).
"""
