"""Train stage: the relightable MVP head and the TRAvatar* baseline from the capture's outputs."""
