"""The science, offline: robots, dynamics, feedback laws, HMPC, datasets, emulator, export."""
