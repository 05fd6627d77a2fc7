"""A small MapAnything for tests: the real model class and heads, a DINOv2-S encoder and 4 alternating-
attention layers instead of ViT-G's 24 + 16, random weights. Parameter values follow the layout of the
repository's Hydra configs (configs/model: mapanything.yaml, task/images_only.yaml, pred_head/dpt_pose_scale.yaml
with adaptor raydirs_depth_pose_confidence_mask_scale); only the sizes are shrunk."""

from __future__ import annotations

from typing import Any

INF = float("inf")


def small_config() -> dict[str, Any]:
    enc = {
        "encoder_str": "dinov2", "name": "dinov2_small_test", "data_norm_type": "dinov2", "size": "small",
        "with_registers": False, "uses_torch_hub": True, "gradient_checkpointing": False,
        "norm_returned_features": False, "keep_first_n_layers": 8,
        "torch_hub_pretrained": False,  # random weights: nothing is downloaded
    }
    info = {
        "model_type": "alternating_attention", "model_return_type": "intermediate_features",
        "custom_positional_encoding": None,
        "module_args": {
            "name": "aat_4_layers_test", "indices": [1, 2], "norm_intermediate": True, "size": "4_layers",
            "depth": 4, "distinguish_ref_and_non_ref_views": True, "gradient_checkpointing": False,
            "dim": 384, "num_heads": 6, "mlp_ratio": 4, "qkv_bias": True, "qk_norm": False, "init_values": 1e-5,
        },
    }
    adaptor = "raydirs+depth+pose+confidence+mask+scale"
    head = {
        "type": "dpt+pose",
        "feature_head": {"feature_dim": 64, "hooks": [0, 1, 2, 3], "checkpoint_gradient": False},
        "regressor_head": {"output_dim": 6, "checkpoint_gradient": False},
        "pose_head": {"num_resconv_block": 2, "rot_representation_dim": 4},
        "scale_head": {"output_dim": 1},
        "adaptor_type": "raydirs+depth+pose+confidence+mask",
        "dpt_adaptor": {
            "name": adaptor, "ray_directions_mode": "linear", "ray_directions_normalize_to_unit_sphere": True,
            "ray_directions_normalize_to_unit_image_plane": False, "ray_directions_vmin": -INF,
            "ray_directions_vmax": INF, "ray_directions_clamp_min_of_z_dir": False,
            "ray_directions_z_dir_min": -INF, "depth_mode": "exp", "depth_vmin": 0, "depth_vmax": INF,
            "confidence_type": "exp", "confidence_vmin": 1, "confidence_vmax": INF,
        },
        "pose_adaptor": {
            "name": adaptor, "cam_trans_mode": "linear", "cam_trans_vmin": -INF, "cam_trans_vmax": INF,
            "quaternions_mode": "linear", "quaternions_normalize": True, "quaternions_vmin": -INF,
            "quaternions_vmax": INF,
        },
        "scale_adaptor": {"name": adaptor, "mode": "exp", "vmin": 1e-8, "vmax": INF},
        "gradient_checkpointing": False,
    }
    task = {
        "ray_dirs_encoder_config": {"name": "ray_dirs_encoder", "in_chans": 3, "encoder_str": "dense_rep_encoder",
                                    "apply_pe": False},
        "depth_encoder_config": {"name": "depth_encoder", "in_chans": 1, "encoder_str": "dense_rep_encoder",
                                 "apply_pe": False},
        "cam_rot_encoder_config": {"name": "cam_rot_quats_encoder", "in_chans": 4, "encoder_str": "global_rep_encoder"},
        "cam_trans_encoder_config": {"name": "cam_trans_encoder", "in_chans": 3, "encoder_str": "global_rep_encoder"},
        "scale_encoder_config": {"name": "scale_encoder", "in_chans": 1, "encoder_str": "global_rep_encoder"},
        "overall_prob": 0, "dropout_prob": 1, "ray_dirs_prob": 0, "depth_prob": 0, "cam_prob": 0,
        "sparse_depth_prob": 0, "sparsification_removal_percent": 0, "depth_scale_norm_all_prob": 0,
        "pose_scale_norm_all_prob": 0,
    }
    return {
        "name": "mapanything", "encoder_config": enc, "info_sharing_config": info, "pred_head_config": head,
        "geometric_input_config": task, "use_register_tokens_from_encoder": False,
        "info_sharing_mlp_layer_str": "mlp",
    }


def small_mapanything() -> Any:
    from mapanything.models import MapAnything

    return MapAnything(**small_config())


def save_small_mapanything(directory: str) -> None:
    """Random-weight small MapAnything in the Hugging Face layout MapAnything.from_pretrained reads:
    config.json (the constructor's arguments) + model.safetensors. (The mixin's own save_pretrained cannot
    serialise the configs once the model has put layer classes into them.)"""
    import copy
    import json
    from pathlib import Path

    from mapanything.models import MapAnything
    from safetensors.torch import save_model

    cfg = small_config()
    model = MapAnything(**copy.deepcopy(cfg))
    # like the released checkpoints' config.json, no torch_hub_pretrained key: loading it back offline only
    # works because the adapter turns the encoder's hub download off
    del cfg["encoder_config"]["torch_hub_pretrained"]
    Path(directory, "config.json").write_text(json.dumps(cfg))
    save_model(model, str(Path(directory, "model.safetensors")))
