"""A tree's measures: the SAH cost model, the validator, quality metrics, the
float32 error bound (numpy only, below the builders they measure)."""
