#!/usr/bin/env python3
# usage: cargo doc -p dpsa-core --no-deps --features alloc --target-dir /tmp/apidoc && python3 tests/api_count.py /tmp/apidoc/doc/dpsa_core
# Counts dpsa-core's public items as rustdoc renders them (reachable from the crate root;
# `cargo doc -p dpsa-core --no-deps --features alloc` into a fresh target/doc/dpsa_core):
# one page per item (rustdoc's redirect stubs skipped), plus the inherent methods and
# associated consts on those pages. `bench/` (the unstable internals) is counted apart.
import re,glob,collections,sys
d=sys.argv[1] if len(sys.argv)>1 else 'target/doc/dpsa_core'
res={}
for part in ('api','bench'):
    kinds=collections.Counter(); meth=0; mods=0
    for f in glob.glob(d+'/**/*.html',recursive=True):
        if ('/bench/' in f) != (part=='bench'): continue
        s=open(f).read()
        if 'http-equiv="refresh"' in s: continue
        b=f.rsplit('/',1)[1]
        if b=='index.html': mods+=1; continue
        if b=='all.html': continue
        kinds[b.split('.')[0]]+=1
        a=s.find('id="implementations-list"')
        if a<0: continue
        e=min([x for x in [s.find('id="trait-implementations"',a),s.find('id="synthetic-implementations"',a)] if x>=0] or [len(s)])
        meth+=len(re.findall(r'id="(?:method|associatedconstant)\.',s[a:e]))
    print(f'{part}: modules {mods}, items {sum(kinds.values())} {dict(sorted(kinds.items()))}, inherent methods + assoc consts {meth}; total {mods+sum(kinds.values())+meth}')
