"""Fields (Sec 4.1-4.2): planes and regularisers, the gear function, the gear field, the proposal field."""
