"""Relighting: the Relightable protocols, target lights and maps, the tensor core, the Relighter, photos."""
