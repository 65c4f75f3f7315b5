"""Streaming services of fingerprint: wire format and message models (pure), and the zenoh nodes
(publisher, processor, recorder, viewer bridge, CLI). zenoh is imported by the nodes only."""
