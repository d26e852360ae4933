"""A tiny third-party codec as an early plugin author wrote it: the block's voxels are its code."""

import sdfcodec


class VoxelCodec(sdfcodec.Codec):
    codec_id = "oldstyle-voxels"
    code_sizes = (4096,)
    prefix_ordered = False
    requires_fit = False

    code_size = 4096

    def __init__(self):
        pass

    def _encode(self, blocks):
        return blocks.reshape(len(blocks), 4096).clone()

    def _decode(self, codes):
        return codes.reshape(len(codes), 16, 16, 16).clone()
