"""Speed: training and inference time, WareSynth throughput, labelling time."""
