"""The streaming nodes (docs/design.md §2, §7): ``publisher``, ``processor``, ``recorder`` (each a
``base.Node`` on an open zenoh session) and ``local.run_pipeline`` (all of them in one process)."""
