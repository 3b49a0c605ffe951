"""Body models behind one interface: the mannequin-x mannequin (default) and SMPL (user-provided files)."""
