"""The paper's fine-tuning augmentation (RackLay §5.5). It lives in `racklay.augment` (one home
for augmentation, shared with `racklay train --augment`); this module keeps transfer's names."""
from racklay.augment import AugmentConfig, PaperAugment, make_augment, paper_augment

__all__ = ["AugmentConfig", "PaperAugment", "paper_augment", "make_augment"]
