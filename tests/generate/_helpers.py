"""Tiny randomly initialised image-to-video pipelines in diffusers layout, built from config
dicts (no weights exist on the test machines, and none may be downloaded): a CogVideoX
image-to-video (1 transformer layer, a 4-block VAE of 8 channels, a 1-layer T5 encoder and a
character-level T5 tokenizer written here) and a Stable Video Diffusion (a 2-block UNet, a
2-block temporal VAE, a 1-layer CLIP vision encoder). They make noise, not video: the tests
check shapes, determinism and plumbing, never content."""

from __future__ import annotations

import string
from pathlib import Path

# CogVideoX: latent 2x4 (x8 VAE) -> 32x16 px, frames 1 + k*4; learned positional embeddings
# as in CogVideoX-5b-I2V, so only that size
# the tiny models' configs: a table, kept as written
# fmt: off
COG_TRANSFORMER = dict(num_attention_heads=2, attention_head_dim=16, in_channels=8, out_channels=4,
                       time_embed_dim=2, text_embed_dim=32, num_layers=1, sample_width=4, sample_height=2,
                       sample_frames=9, patch_size=2, temporal_compression_ratio=4, max_text_seq_length=16,
                       use_rotary_positional_embeddings=True, use_learned_positional_embeddings=True)
COG_VAE = dict(down_block_types=("CogVideoXDownBlock3D",) * 4, up_block_types=("CogVideoXUpBlock3D",) * 4,
               block_out_channels=(8, 8, 8, 8), latent_channels=4, layers_per_block=1, norm_num_groups=2,
               temporal_compression_ratio=4)
T5 = dict(d_model=32, d_kv=8, d_ff=37, num_layers=1, num_heads=4, relative_attention_num_buckets=8)
SVD_UNET = dict(block_out_channels=(32, 32), layers_per_block=1, sample_size=16, in_channels=8, out_channels=4,
                down_block_types=("CrossAttnDownBlockSpatioTemporal", "DownBlockSpatioTemporal"),
                up_block_types=("UpBlockSpatioTemporal", "CrossAttnUpBlockSpatioTemporal"),
                cross_attention_dim=16, num_attention_heads=2, projection_class_embeddings_input_dim=48,
                addition_time_embed_dim=16, num_frames=6, transformer_layers_per_block=1)
SVD_VAE = dict(block_out_channels=(32, 32), in_channels=3, out_channels=3, layers_per_block=1,
               down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"), latent_channels=4)
CLIP_VISION = dict(hidden_size=16, projection_dim=16, num_hidden_layers=1, num_attention_heads=2, image_size=224,
                   intermediate_size=24, patch_size=32)  # SVD scales the image to 224 px for CLIP itself
# fmt: on


def tokenizer():
    """A T5 tokenizer over lower-case letters, digits and a few marks (a Unigram vocabulary)."""
    from transformers import T5Tokenizer

    pieces = list(string.ascii_lowercase + string.digits + ".,;:'-()")
    vocab = [("<pad>", 0.0), ("</s>", 0.0), ("<unk>", 0.0), ("\u2581", -2.0)]
    vocab += [(p, -3.0) for p in pieces] + [("\u2581" + p, -3.0) for p in pieces]
    return T5Tokenizer(vocab=vocab, extra_ids=0)


def cogvideox(folder: Path) -> Path:
    import torch
    from diffusers import (
        AutoencoderKLCogVideoX,
        CogVideoXDDIMScheduler,
        CogVideoXImageToVideoPipeline,
        CogVideoXTransformer3DModel,
    )
    from transformers import T5Config, T5EncoderModel

    tok = tokenizer()
    torch.manual_seed(0)
    pipe = CogVideoXImageToVideoPipeline(
        tokenizer=tok,
        text_encoder=T5EncoderModel(T5Config(vocab_size=len(tok), **T5)),
        vae=AutoencoderKLCogVideoX(**COG_VAE),
        transformer=CogVideoXTransformer3DModel(**COG_TRANSFORMER),
        scheduler=CogVideoXDDIMScheduler(),
    )
    pipe.save_pretrained(folder)
    return folder


def svd(folder: Path) -> Path:
    import torch
    from diffusers import (
        AutoencoderKLTemporalDecoder,
        EulerDiscreteScheduler,
        StableVideoDiffusionPipeline,
        UNetSpatioTemporalConditionModel,
    )
    from transformers import CLIPImageProcessor, CLIPVisionConfig, CLIPVisionModelWithProjection

    torch.manual_seed(0)
    pipe = StableVideoDiffusionPipeline(
        vae=AutoencoderKLTemporalDecoder(**SVD_VAE),
        image_encoder=CLIPVisionModelWithProjection(CLIPVisionConfig(**CLIP_VISION)),
        unet=UNetSpatioTemporalConditionModel(**SVD_UNET),
        scheduler=EulerDiscreteScheduler(
            beta_start=0.00085,
            beta_end=0.012,
            beta_schedule="scaled_linear",
            prediction_type="v_prediction",
            sigma_max=700.0,
            sigma_min=0.002,
            steps_offset=1,
            timestep_spacing="leading",
            timestep_type="continuous",
            use_karras_sigmas=True,
        ),
        feature_extractor=CLIPImageProcessor(crop_size=16, size=16),
    )
    pipe.save_pretrained(folder)
    return folder
