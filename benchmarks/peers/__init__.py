"""Peer codes run side by side with regolith-cosim (speed and cross-checks).

Each peer lives in its own module and imports its heavy dependency lazily, so
importing this package never requires the peer to be installed.
"""
