"""bcf.core: the library. BC6H codec (`bc6h`), texture containers (`containers`), image files and mip
chains (`images`), texture-level BC6H tools: encode a mip chain, verify, mode histogram (`bc6h_tools`)."""
