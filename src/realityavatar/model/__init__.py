"""Avatar components (Gaussians, pose encoder, temporal module, deformer, skinning, colour) and the LightningModule."""
