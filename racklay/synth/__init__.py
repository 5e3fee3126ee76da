"""WareSynth: procedural warehouse-rack scenes rendered with moderngl/EGL, with exact ground
truth (RackLay layouts, depth, normals, semantic/instance masks, 2D/3D boxes, COCO, KITTI).

    from racklay.synth import load_recipe, generate_dataset
    generate_dataset(load_recipe("complex"), n=100, out="datasets/generated/complex", seed=0)
"""
from .recipe import Recipe, RecipeError, load_recipe, recipe_from_dict

__all__ = ["Recipe", "RecipeError", "load_recipe", "recipe_from_dict", "generate_dataset", "sample_scene"]


def __getattr__(name):
    if name == "generate_dataset":
        from .generate import generate_dataset
        return generate_dataset
    if name == "sample_scene":
        from .scene import sample_scene
        return sample_scene
    raise AttributeError(name)
