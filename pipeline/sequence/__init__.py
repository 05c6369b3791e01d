"""The image-sequence LSTM of seed 000 section 3.3: frame features, training, sequence database."""
