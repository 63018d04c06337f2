"""The three classes of digging trajectory (PAPER.md: where the dig starts, its initial bucket
angle, its shape) and the name of a dig that is none of them. Defined once; the analysis
classifies into them, the synthetic digs are drawn from them, the fleet counts them."""

DIG_CLASSES = ("Type 1", "Type 2", "Type 3")
OTHER = "other"
