"""Free-viewpoint tracking (Sec 4.5): click geometry, propagation, metrics, viewer control, ns-gear-track."""
