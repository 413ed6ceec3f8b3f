"""Single-view voxels: a photo of one object (with its mask) to a 32^3 occupancy grid (`nerfpipe voxels`).

Not a method of the method interface (`model.methods`): a method turns a posed capture into a run that renders
rays; this network turns unposed photos into a volume, with no cameras and no per-scene training (docs/VOXELS.md).
- `inputs`: the one way a photo becomes the network's input (crop to the mask, square, background removed);
- `net`: the encoder-decoder (`VoxelNet`);
- `fuse`: grids of several photos of one object, turned into the first photo's frame and merged;
- `weights`: weights files and the shipped `weights/pretrained.pt`;
- `pretrain`: the step `pretrain-voxels` runs on the one training loop.
"""
