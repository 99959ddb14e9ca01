"""Long videos as a sequence of chunks, each a model of its own (`ns-gear-chunks`)."""
