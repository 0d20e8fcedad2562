"""The communication channel (COM): each site's port, the packets, the links between sites
(in-process, impaired, Zenoh), and the two-port as a whole (wave-variable and direct)."""
