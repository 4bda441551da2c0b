"""hil: a distributed publish/subscribe hardware-in-the-loop rig for INS/GNSS navigation."""

__version__ = "0.1.0"
