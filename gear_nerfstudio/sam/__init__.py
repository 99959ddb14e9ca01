"""SAM behind one small interface (Sec 4.2): an image encoder and a prompt decoder."""
